"""GSCLO scheduler (paper problem P_GS): problem type, Rician channel model, methods and ``solve``.

Pure library (numpy, scipy, cvxpy; no rclpy)::

    from gsrmr_server.scheduling import ChannelModel, Problem, solve
    gains = ChannelModel(seed=1).gains(distances_m)
    sched = solve(Problem(channel_gain=gains, gs_loss=losses, loss_threshold=0.03), "exact")
"""

from gsrmr_common.channel import ChannelModel
from gsrmr_common.link_model import energy_j, rate_bps, required_power_w
from gsrmr_server.scheduling.problem import Problem, ProblemError, Schedule
from gsrmr_server.scheduling.solve import METHODS, solve

__all__ = ["METHODS", "ChannelModel", "Problem", "ProblemError", "Schedule", "energy_j", "rate_bps",
           "required_power_w", "solve"]
