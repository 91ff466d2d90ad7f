"""The CPU Gaussian-splatting engine: the model and its .ply, ``render``, training, compaction, alignment and pose
import. Conventions (OpenCV camera axes, pixel centres at +0.5, 3DGS compositing) and design: docs/splatting.md.
"""

from gsrmr_common.interrupts import guard_console_start_up

guard_console_start_up()  # a console script of this package: Ctrl-C while its module loads exits 0
