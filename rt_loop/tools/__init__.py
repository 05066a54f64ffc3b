"""The tools that drive a loop from outside, apart from the loop they drive.

``bench`` (scripts/bench-loop: the loop against the machine's wake-up floor),
``doctor`` (dct-hil doctor: is this machine fit for real time), ``fuzz``
(scripts/fuzz: hostile traffic, every frame accounted for), ``soak``
(scripts/soak: hours of serving with memory watched), ``faults_bench`` (what
failure simulation costs the tick), ``xcp_bench`` (what XCP measurement costs
the tick). Each starts a server (or a bare loop) the way a user would and
judges it from outside; nothing in the loop imports them.
"""
