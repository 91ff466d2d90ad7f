"""The scheduler (GSCLO, the paper's problem P_GS): the problem, its solvers, the online planner, the loss map and
predictor, and the ROS node that publishes the plan. Design: ``docs/scheduling.md``.

The solvers and the planner import no ROS; only ``scheduler_node`` does::

    from gsrmr_common.channel import ChannelModel
    from gsrmr_scheduler.problem import Problem
    from gsrmr_scheduler.solve import solve
    gains = ChannelModel(seed=1).gains(distances_m)
    sched = solve(Problem(channel_gain=gains, gs_loss=losses, loss_threshold=0.03), "exact")
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
