"""Subnormal floats flushed to zero in every job (the CPU's FTZ and DAZ modes, ``torch.set_flush_denormal``).

A float32 below 2^-126 (1.18e-38) is subnormal. x86 CPUs compute with such values through a slow microcode path,
tens to hundreds of times slower than with normal numbers, and training makes them as a matter of course. An Adam
optimizer does: a weight whose gradient is zero for a while (a first-layer weight of a cell without demand, a dead
ReLU) keeps first and second moments that shrink geometrically by beta1 = 0.9 and beta2 = 0.999 per step, through
the subnormal range, for ~150 and ~16,000 steps. So do exponentials of large negative arguments in a forward pass
(the world model's compiled loss and gradient ran ~1.3x faster flushed). SAC at the paper's sizes (a 2,914-wide
input, two [256, 256] critics) slowed from 21 to 15 gradient steps per second within its benchmark's first ~1,700
steps, the spread of its repeats on the 2-core machine (README, Benchmarks).

Flushed, such a value is 0 (FTZ: results; DAZ: inputs). What that changes is below float32's resolution of every
value a job records (an Adam step of a subnormal moment moves a weight by ~1e-35): the demo's `tables` run gave
the same 66 per-day results and byte-identical tables with and without it. The mode is a property of a
thread: it is set before torch or numba start their worker threads, which inherit it (POSIX threads inherit the
floating-point environment of the thread that creates them). It applies to every float operation of the thread,
Python's and numpy's float64 too (below 2.2e-308); hypothesis refuses to draw floats under it, so the tests keep
the default mode (tests/conftest.py).
"""
from __future__ import annotations

import torch


def flush_subnormals() -> bool:
    """Set FTZ and DAZ on this thread (again, where it was set before). Returns False (and changes nothing) where
    the CPU has no such mode."""
    return bool(torch.set_flush_denormal(True))
