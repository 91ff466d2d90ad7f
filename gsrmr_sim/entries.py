"""Console scripts of the simulator's ROS nodes (setup.py): light entries that import the node module inside
the interrupt guard of :func:`gsrmr_common.interrupts.node_entry`, so Ctrl-C exits 0 in every phase."""

from gsrmr_common.interrupts import node_entry

mock_limo = node_entry("gsrmr_sim.limo.mock:main")
mock_camera = node_entry("gsrmr_sim.world.camera_node:main")
route_follower = node_entry("gsrmr_sim.world.route_follower:main")
uplink_relay = node_entry("gsrmr_sim.fault_relay:main")
sim_channel = node_entry("gsrmr_sim.world.channel_node:main")
