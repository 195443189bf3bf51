"""A run's MCAP log: the recorder that writes it, and the readers that view and export it."""
