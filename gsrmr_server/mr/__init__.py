"""The server's MR content: the virtual world composited into the robot's view.

:mod:`content` — the virtual agents and their lighting (``config/mr/<name>.yaml``), the
:class:`~gsrmr_server.mr.content.VirtualViewSource` interface and its built-in implementation
:class:`~gsrmr_server.mr.content.AgentsView`; :mod:`blend` — the mask d_t and ``m = d·r + (1 − d)·v``.
Imports no ROS and nothing of the simulator.
"""
