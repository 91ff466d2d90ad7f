"""Robot side of gsrmr: the LIMO base driver and the robot node (image or pose key each slot)."""
