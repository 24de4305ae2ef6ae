"""Compiled CPU kernel of the nearest-available-UAV association (``dswm.sim.physics.associate`` on CPU).

The association rule is the one of docs/PROTOCOL.md §2: every cell is served by the available UAV at the smallest
horizontal distance, ties going to the lowest UAV index. Written with tensor operations it materializes the
(candidate, UAV, cell) distances and several same-sized temporaries: for the planner's 512 candidates, 16 UAVs
and 400 cells that is 3.3M triples per imagined step, and memory traffic, not arithmetic, bounds it. The kernel
below makes one pass per candidate with a running minimum per cell kept in cache, in parallel over candidates.

It computes the squared distance exactly as the tensor version does (dx * dx + dy * dy with dx = cell - UAV,
each operation rounded in the input dtype, no fused multiply-add), so the two agree index for index and
distance for distance (``tests/test_physics.py`` checks it).

Compiling the kernels costs a fresh process ~2 s for its first input dtype and ~1.3 s for another on this project's
2-core machine, and every job of the workflow is a process of its own: numba caches the compiled code on disk
(``cache=True``), in ``__pycache__`` beside this file (where Python keeps its bytecode; numba's user-wide cache
directory where that is not writable, ``NUMBA_CACHE_DIR`` where set). A later process loads it in ~0.3 s. The
cache is keyed by this file's time stamp, the numba version and the CPU, and written by rename, so jobs starting
side by side do not read a half-written one.
Nothing under ``results/`` is written, so the read-only audit is unaffected.
"""
from __future__ import annotations

import numba
import numpy as np
import torch


@numba.njit(boundscheck=False, cache=True)
def _nearest_row(px, py, avail, cx, cy, out_idx, out_d2, i):  # pragma: no cover - compiled
    """Candidate i: running minimum over its UAVs for every cell."""
    k = px.shape[1]
    g = cx.shape[0]
    best = np.full(g, np.inf, dtype=px.dtype)
    idx = np.zeros(g, dtype=np.int64)
    any_available = False
    for j in range(k):
        if avail[i, j]:
            any_available = True
            x = px[i, j]
            y = py[i, j]
            for c in range(g):
                dx = cx[c] - x
                dy = cy[c] - y
                d = dx * dx + dy * dy
                closer = d < best[c]              # strict: an equal distance keeps the lower index
                best[c] = d if closer else best[c]
                idx[c] = j if closer else idx[c]
    if k > 0 and not any_available:                # index 0 and its distance
        for c in range(g):
            dx = cx[c] - px[i, 0]
            dy = cy[c] - py[i, 0]
            best[c] = dx * dx + dy * dy
    for c in range(g):
        out_idx[i, c] = idx[c]
        out_d2[i, c] = best[c]


# Two entry points: the serial one starts no thread pool, so single-threaded jobs running side by side do not
# fight over cores (numba's OpenMP workers spin after each call).
@numba.njit(parallel=True, boundscheck=False, cache=True)
def _nearest_parallel(px, py, avail, cx, cy, out_idx, out_d2):  # pragma: no cover - compiled
    for i in numba.prange(px.shape[0]):
        _nearest_row(px, py, avail, cx, cy, out_idx, out_d2, i)


@numba.njit(boundscheck=False, cache=True)
def _nearest_serial(px, py, avail, cx, cy, out_idx, out_d2):  # pragma: no cover - compiled
    for i in range(px.shape[0]):
        _nearest_row(px, py, avail, cx, cy, out_idx, out_d2, i)


def nearest_available(pos: torch.Tensor, available: torch.Tensor,
                      cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest available UAV of every cell and its squared horizontal distance.

    Args: pos (N, K, 2) CPU tensor in metres; available (N, K) bool; cells (G, 2).
    Returns: ((N, G) int64 UAV index, 0 where no UAV is available; (N, G) squared horizontal distance in m^2
        to that UAV, in pos's dtype, not differentiable).
    Runs on min(torch's intra-op threads, numba's thread pool) threads; on one thread without a thread pool.
    Inside a graph compiled by ``torch.compile`` (the planner's imagined step, ``planner.compile``) it is the
    torch operator ``dswm::nearest_available``, one opaque step of the graph. Eager code calls the kernel
    directly, which saves the operator's dispatch (~25 us, paid per call by the proposal search's many small
    batches).
    """
    if torch.compiler.is_compiling():
        return _nearest_op(pos, available, cells)
    return _nearest(pos, available, cells)


def _nearest(pos: torch.Tensor, available: torch.Tensor,
             cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``nearest_available`` by the numba kernels."""
    threads = min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS)
    if threads > 1 and numba.get_num_threads() != threads:
        numba.set_num_threads(threads)
    kernel = _nearest_parallel if threads > 1 else _nearest_serial
    p = pos.detach()
    c = cells.detach().to(p.dtype)
    n, g = p.shape[0], c.shape[0]
    idx = torch.empty((n, g), dtype=torch.int64)
    d2 = torch.empty((n, g), dtype=p.dtype)
    kernel(p[..., 0].contiguous().numpy(), p[..., 1].contiguous().numpy(),
           available.detach().to(torch.bool).contiguous().numpy(),
           c[:, 0].contiguous().numpy(), c[:, 1].contiguous().numpy(), idx.numpy(), d2.numpy())
    return idx, d2


@torch.library.custom_op("dswm::nearest_available", mutates_args=())
def _nearest_op(pos: torch.Tensor, available: torch.Tensor,
                cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``_nearest`` as the torch operator ``dswm::nearest_available`` (for compiled graphs)."""
    return _nearest(pos, available, cells)


@_nearest_op.register_fake
def _nearest_op_shapes(pos, available, cells):
    """Output shapes and dtypes for tracing."""
    n, g = pos.shape[0], cells.shape[0]
    return pos.new_empty((n, g), dtype=torch.int64), pos.new_empty((n, g))
