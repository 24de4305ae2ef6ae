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
from pathlib import Path
from typing import Literal

import torch
from torch import nn

MatmulDtype = Literal["float32", "bfloat16"]
"""The values of ``matmul_dtype`` (a settings field of this type states them as its constraint)."""
MATMUL_DTYPES = dict(zip(typing.get_args(MatmulDtype), (torch.float32, torch.bfloat16)))
"""The torch dtype of each value of :data:`MatmulDtype`."""

BFLOAT16_CPU_FLAGS = ("avx512_bf16", "amx_bf16", "bf16")
"""The CPU flags of /proc/cpuinfo that name native bfloat16 dot products: x86's AVX512-BF16 and AMX-BF16, Arm's
BF16 (its ``Features`` line)."""


def native_bfloat16(cpuinfo: str | Path = "/proc/cpuinfo") -> bool | None:
    """Whether this CPU computes bfloat16 dot products natively (:data:`BFLOAT16_CPU_FLAGS`), from ``cpuinfo``:
    True or False, None where the file cannot be read (not Linux). Where it is False, torch emulates bfloat16
    products, and a bfloat16 GEMM runs several times SLOWER than float32's (a 256 x 3,010 by 3,010 x 256 product on
    one core of an AVX-512 Xeon without AVX512-BF16: 13.2 ms against 2.8 ms)."""
    try:
        text = Path(cpuinfo).read_text()
    except OSError:
        return None
    flags = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip().lower() in ("flags", "features"):
            flags.update(value.split())
    return bool(flags.intersection(BFLOAT16_CPU_FLAGS)) if flags else None


def emulated_bfloat16_warning(key: str, matmul_dtype: str | None, device: str,
                              native: bool | None = None) -> str | None:
    """The warning a job prints where the setting ``key`` (``methods.<m>.matmul_dtype``) asks for bfloat16 products
    on a CPU without native ones (:func:`native_bfloat16`, or ``native`` where given), else None. Results do not
    change with it; the job's time does."""
    if matmul_dtype != "bfloat16" or not str(device).startswith("cpu"):
        return None
    if native is None:
        native = native_bfloat16()
    if native is not False:
        return None
    return (f"{key}: bfloat16 products on a CPU without native bfloat16 dot products ({', '.join(BFLOAT16_CPU_FLAGS)} "
            "absent from /proc/cpuinfo): torch emulates them, several times slower than float32. The results are "
            f"those of the setting; for speed on this CPU set {key}: float32 (its results differ by the rounding)")


def autocast(device_type: str, name: str) -> torch.autocast:
    """torch's autocast to the products' dtype of ``name`` (a :data:`MatmulDtype`) on ``device_type``; off for
    float32, where every operation stays as it is. For networks run whole under autocast (GA-MATR's policy, TD-MPC's
    losses and MPPI) rather than layer by layer (:class:`MatmulLinear`)."""
    dtype = MATMUL_DTYPES[name]
    return torch.autocast(device_type, dtype=dtype, enabled=dtype != torch.float32)


def linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None = None,
           dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """``x @ weight.T + bias`` in float32, its product computed in ``dtype`` (see the module's docstring)."""
    if dtype == torch.float32:
        return nn.functional.linear(x, weight, bias)
    y = nn.functional.linear(x.to(dtype), weight.to(dtype)).float()
    return y if bias is None else y + bias


class _Product(torch.autograd.Function):
    """``x @ weight.T`` in the dtype of ``low_weight`` (``weight`` rounded to it, kept by the caller), returned as
    float32: :func:`linear`'s product and gradients, value for value, without rounding ``weight`` again.

    ``x_low``, when given, is the input already rounded whose last columns are ``x`` rounded: the product reads
    it, and only ``x``'s columns get a gradient (a critic's observation beside its action).

    The backward pass computes what autograd computes for :func:`linear`: the output's gradient rounded to the
    low dtype, ``grad @ W`` for the input and ``grad.T @ x`` for the weight, returned as float32 (the input's
    gradient in the input's dtype)."""

    @staticmethod
    def forward(ctx, x_low, x, weight, low_weight):
        if x_low is None:
            x_low = x.to(low_weight.dtype)
        ctx.save_for_backward(x_low, low_weight)
        ctx.first = x_low.shape[1] - x.shape[1]
        ctx.x_dtype = x.dtype
        return nn.functional.linear(x_low, low_weight).float()

    @staticmethod
    def backward(ctx, grad):
        x_low, low_weight = ctx.saved_tensors
        grad_low = grad.to(low_weight.dtype)
        grad_x = grad_weight = None
        if ctx.needs_input_grad[1]:
            w = low_weight if ctx.first == 0 else low_weight[:, ctx.first:]
            grad_x = grad_low.mm(w).to(ctx.x_dtype)
        if ctx.needs_input_grad[2]:
            grad_weight = grad_low.t().mm(x_low).float()
        return None, grad_x, grad_weight, None


class MatmulLinear(nn.Linear):
    """``nn.Linear`` with its product in ``matmul_dtype`` (:func:`linear`); the same parameters and state dict.

    Between :func:`keep_casts` ``(module, True)`` and ``(module, False)`` a low-precision layer rounds its weight
    once and reuses the rounded copy until :func:`forget_casts` drops it: the owner of the weight calls that after
    every change of the weight (an optimizer step, a Polyak update), which nothing else can detect (torch's fused
    Adam updates a parameter without bumping its version counter)."""

    matmul_dtype: torch.dtype = torch.float32
    keep_cast: bool = False
    _low_weight: torch.Tensor | None = None

    def low_weight(self) -> torch.Tensor:
        """The weight rounded to ``matmul_dtype``, detached (the kept copy while casts are kept)."""
        if self._low_weight is not None:
            return self._low_weight
        w = self.weight.detach().to(self.matmul_dtype)
        if self.keep_cast:
            self._low_weight = w
        return w

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.matmul_dtype == torch.float32 or not self.keep_cast:
            return linear(x, self.weight, self.bias, self.matmul_dtype)
        return self._bias(_Product.apply(None, x, self.weight, self.low_weight()))

    def forward_tail(self, x_low: torch.Tensor, tail: torch.Tensor) -> torch.Tensor:
        """The layer on ``x_low``, its whole input already in ``matmul_dtype``, whose last columns are ``tail``
        rounded to it; the gradient goes to ``tail`` only (a critic's observation, which needs none, beside its
        action). The same values as ``forward`` on that input."""
        if x_low.dtype != self.matmul_dtype:
            raise ValueError(f"forward_tail: expected the input in {self.matmul_dtype}, found {x_low.dtype}")
        if self.matmul_dtype == torch.float32:
            return self.forward(torch.cat([x_low[:, :x_low.shape[1] - tail.shape[1]], tail], dim=1))
        return self._bias(_Product.apply(x_low, tail, self.weight, self.low_weight()))

    def _bias(self, y: torch.Tensor) -> torch.Tensor:
        return y if self.bias is None else y + self.bias


def keep_casts(module: nn.Module, keep: bool) -> None:
    """Let every :class:`MatmulLinear` of ``module`` keep its rounded weight (``keep``) or not; either way the
    copies kept so far are dropped."""
    for sub in module.modules():
        if isinstance(sub, MatmulLinear):
            sub.keep_cast = keep
            sub._low_weight = None


def forget_casts(module: nn.Module) -> None:
    """Drop the rounded weights kept by ``module``'s layers: call after every change of its parameters."""
    for sub in module.modules():
        if isinstance(sub, MatmulLinear):
            sub._low_weight = None


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
