"""Library: textured boxes and cylinders, their YAML schema (:mod:`spec`) and a numba ray caster
(:mod:`raycast`). Shared by the simulated world and the server's virtual MR content; imports no ROS."""
