"""Running a student's loop: the supervisor and its parts (launch, watch, read, control, end), the sandbox's limits, run records."""
