"""The controllers (algorithms, no FMI): PI, NNPC, MPC, explicit policy and their C twins."""

from cosim.base.numeric_env import pin as _pin_numeric_kernels

_pin_numeric_kernels()  # before torch or numpy is imported (cosim/base/numeric_env.py)
