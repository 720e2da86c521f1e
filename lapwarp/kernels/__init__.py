"""Warp kernels and functions only (``@wp.kernel`` / ``@wp.func``); no Python-side state lives here.

Each module is one Warp module: keep them few and stable, since Warp compiles per module and cold
compiles dominate CPU test time. Modules set ``enable_backward=False`` unless a gradient is needed.
"""
