"""The number format of a learner's matrix products (config ``matmul_dtype`` of ``methods.sac`` and
``methods.maddpg``).

* ``float32``: every product in float32, as torch does by default.
* ``bfloat16``: a Linear layer rounds its input and its weight to bfloat16 for the product (the GEMM accumulates
  in float32), returns the product as float32 and adds its bias in float32. Parameters, their gradients, the
  optimizers' state, the activations between layers, the losses and every other operation stay float32
  (mixed precision with float32 master weights). On a CPU with native bfloat16 dot products (avx512_bf16, AMX)
  the GEMMs run 3-5x faster than in float32; elsewhere they are emulated and may be slower.

The rounding is per product: an input rounds to 8 significant bits (relative error <= 2^-9), the sum over a
layer's inputs keeps float32 accuracy, and the result rounds once more to bfloat16 before the bias.
"""
from __future__ import annotations

import typing
from typing import Literal

import torch
from torch import nn

MatmulDtype = Literal["float32", "bfloat16"]
"""The values of ``matmul_dtype`` (a settings field of this type states them as its constraint)."""
MATMUL_DTYPES = dict(zip(typing.get_args(MatmulDtype), (torch.float32, torch.bfloat16)))
"""The torch dtype of each value of :data:`MatmulDtype`."""


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None,
           dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``x @ weight.T + bias`` in float32, its product computed in ``dtype`` (see the module's docstring)."""
    if dtype == torch.float32:
        return nn.functional.linear(x, weight, bias)
    y = nn.functional.linear(x.to(dtype), weight.to(dtype)).float()
    return y if bias is None else y + bias


class MatmulLinear(nn.Linear):
    """``nn.Linear`` with its product in ``matmul_dtype`` (:func:`linear`); the same parameters and state dict."""

    matmul_dtype: torch.dtype = torch.float32

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return linear(x, self.weight, self.bias, self.matmul_dtype)


def set_matmul_dtype(module: nn.Module, name: str) -> nn.Module:
    """Make every ``nn.Linear`` in ``module`` a :class:`MatmulLinear` computing in the dtype named ``name`` (a key
    of :data:`MATMUL_DTYPES`), in place (parameters untouched); returns ``module``."""
    if name not in MATMUL_DTYPES:
        raise ValueError(f"matmul_dtype: expected one of {sorted(MATMUL_DTYPES)}, found {name!r}")
    for sub in module.modules():
        if isinstance(sub, nn.Linear):
            sub.__class__ = MatmulLinear
            sub.matmul_dtype = MATMUL_DTYPES[name]
    return module
