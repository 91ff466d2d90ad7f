"""The scheduler (GSCLO, the paper's problem P_GS): the problem and its solvers (one entry point,
:func:`gsrmr_scheduler.solve.solve`), the online planner, the loss map and predictor, and the ROS node that publishes
the plan — the only module here that imports ROS. Design: ``docs/scheduling.md``.
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
