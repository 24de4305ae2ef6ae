"""served_ratio for N candidate fleets: forward and forward+backward, against an all-pairs reference.

Run: python benchmarks/bench_physics.py   (writes benchmarks/results/physics.json)
Targets on a 2-core machine: forward <= 10 ms, forward+backward <= 25 ms, >= 3x faster than all-pairs.
"""
from __future__ import annotations

import argparse
import dataclasses

import torch

from _timing import spread_ms, write
from dswm.pipeline.setup import prepare_process
from dswm.sim.env import default_scenario
from dswm.sim.physics import ServiceParams, associate, path_loss_db, served_ratio


def served_ratio_all_pairs(demand, pos, available, cells, *, params):
    """Straightforward reference: path loss and rate for EVERY (candidate, cell, UAV) pair, then select."""
    n, k, _ = pos.shape
    x = demand.expand(n, -1)
    diff = cells.unsqueeze(0).unsqueeze(2) - pos.unsqueeze(1)  # (N, G, K, 2)
    dist = torch.sqrt((diff**2).sum(-1) + params.altitude_m**2)
    gain = torch.pow(10.0, -path_loss_db(dist, params) / 10.0)  # (N, G, K)
    assoc = dist.masked_fill(~available.unsqueeze(1), float("inf")).argmin(-1)
    weight_sum = torch.zeros(n, k, dtype=pos.dtype).scatter_add(1, assoc, x)
    share = params.bandwidth_hz * x / torch.gather(weight_sum, 1, assoc).clamp(min=1e-30)
    g = torch.gather(gain, 2, assoc.unsqueeze(-1)).squeeze(-1)
    rate = share * torch.log2(1 + params.tx_power_w * g / (params.noise_psd_w_per_hz * share.clamp(min=1e-30)))
    f = torch.where(x > 0, torch.clamp(rate / (x.clamp(min=1e-30) * params.demand_intensity * params.r0_bps),
                                       max=1.0), torch.zeros_like(x))
    return (x * f).sum(-1) / x.sum(-1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--n", type=int, default=512)
    ap.add_argument("--k", type=int, default=16)
    ap.add_argument("--side", type=int, default=20, help="grid side; G = side^2")
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    prepare_process(args.threads)   # as every job does (dswm.pipeline.setup.init_process)
    gen = torch.Generator().manual_seed(0)
    side, cell = args.side, 235.0
    r, c = torch.meshgrid(torch.arange(side), torch.arange(side), indexing="ij")
    cells = torch.stack([(c + 0.5) * cell, (r + 0.5) * cell], -1).reshape(-1, 2).float()
    demand = torch.rand(side * side, generator=gen) ** 3
    pos = torch.rand(args.n, args.k, 2, generator=gen) * side * cell
    avail = torch.rand(args.n, args.k, generator=gen) > 0.2
    # the config's service constants, at a fixed u of 40 (the figure does not depend on the calibration)
    params = dataclasses.replace(ServiceParams.from_scenario(default_scenario()), demand_intensity=40.0)

    ref = served_ratio_all_pairs(demand, pos, avail, cells, params=params)
    new = served_ratio(demand, pos, avail, cells, params=params)
    max_diff = float((ref - new).abs().max())
    assert max_diff < 1e-4, f"all-pairs reference and served_ratio differ by {max_diff}"

    with torch.no_grad():
        fwd = spread_ms(lambda: served_ratio(demand, pos, avail, cells, params=params))
        fwd_ref = spread_ms(lambda: served_ratio_all_pairs(demand, pos, avail, cells, params=params))
        assoc = spread_ms(lambda: associate(pos, avail, cells))
    pos_g = pos.clone().requires_grad_(True)
    pos_r = pos.clone().requires_grad_(True)

    def fb(fn, p):
        def run():
            p.grad = None
            fn(demand, p, avail, cells, params=params).sum().backward()
        return run

    fwd_bwd = spread_ms(fb(served_ratio, pos_g))
    fwd_bwd_ref = spread_ms(fb(served_ratio_all_pairs, pos_r))
    write("physics", {
        "shape": {"N": args.n, "K": args.k, "G": side * side},
        "forward_ms": fwd["median_ms"], "forward_backward_ms": fwd_bwd["median_ms"],
        "association_only_ms": assoc["median_ms"],
        "all_pairs_forward_ms": fwd_ref["median_ms"], "all_pairs_forward_backward_ms": fwd_bwd_ref["median_ms"],
        "speedup_forward": round(fwd_ref["median_ms"] / fwd["median_ms"], 2),
        "speedup_forward_backward": round(fwd_bwd_ref["median_ms"] / fwd_bwd["median_ms"], 2),
        "spread_ms": {"forward": fwd, "forward_backward": fwd_bwd, "association_only": assoc,
                      "all_pairs_forward": fwd_ref, "all_pairs_forward_backward": fwd_bwd_ref},
        "max_abs_difference_vs_all_pairs": max_diff,
        "targets": {"forward_ms": 10, "forward_backward_ms": 25, "speedup": 3},
    })


if __name__ == "__main__":
    main()
