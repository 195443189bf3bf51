"""One connected vehicle: perception, spatial reasoning, scheduling, fusion, planning, control."""
