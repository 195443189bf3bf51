"""World server: sim time, pymunk physics, road map, scenarios, LiDAR, the outcome judge."""
