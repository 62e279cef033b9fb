"""A simulated UR10e controller that unmodified ur-rtde connects to.

The simulator runs as its own process (ur-rtde's constructors hold the GIL, so
a simulator in the same process would deadlock them) and binds one loopback
address, so every test can take its own and the fixed UR ports never collide.
"""

from __future__ import annotations
