"""Differentiable weight statistics: the offline detector's features (:func:`seqtrojan.defense.offline.weight_features`)
computed in torch, so that an attacker can hold them at a clean model's values while training (weight camouflage).

Same names, same definitions, float64 throughout (the other sequence models: see :func:`weight_features`): per gate
(input, forget, cell, output) of the first and the last LSTM layer, moments of the input weights, the recurrent weights
and the summed biases (mean, population std + 1e-12, max |w|, RMS, skewness, excess kurtosis); for the weight blocks,
the largest singular value over the RMS and the effective rank (exp of the entropy of the normalised squared singular
values); for the first layer, the norm of the input weights reading each cell code over the mean of those norms. The
singular values come from ``torch.linalg.svdvals``, whose gradient is stable even for repeated values; max |w| has the
subgradient of the largest entry; square roots add 1e-24 inside, so that a constant block (a freshly initialised bias)
has finite gradients. Tested equal to the numpy features to 1e-5.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TYPE_CHECKING

import torch

from seqtrojan.cell_types import layer_class
from seqtrojan.env.codes import CELL_NAMES, NUM_CHANNELS

if TYPE_CHECKING:  # the network's cells import this module
    from seqtrojan.agent.network import RecurrentActorCritic

GATES = ("input", "forget", "cell", "output")
GRU_GATES = ("reset", "update", "new")
ATTENTION_BLOCKS = ("input", "qkv", "out", "mlp_in", "mlp_out")
"""a Transformer layer's linear maps (:class:`seqtrojan.agent.cells.transformer.WindowAttentionLayer`)"""


def _sqrt(x: torch.Tensor) -> torch.Tensor:
    """sqrt with a finite gradient at 0 (it adds 1e-24, below float64 resolution of any weight statistic > 1e-8)."""
    return (x + 1e-24).sqrt()


def _moments(w: torch.Tensor) -> dict[str, torch.Tensor]:
    w = w.reshape(-1)
    mean = w.mean()
    std = _sqrt(((w - mean) ** 2).mean()) + 1e-12
    z = (w - mean) / std
    return {
        "mean": mean, "std": std, "absmax": w.abs().max(), "rms": _sqrt((w**2).mean()),
        "skew": (z**3).mean(), "kurtosis": (z**4).mean() - 3.0,
    }  # fmt: skip


def _spectral(w: torch.Tensor) -> dict[str, torch.Tensor]:
    s = torch.linalg.svdvals(w)  # descending
    rms = _sqrt((w**2).mean()) + 1e-12
    p = s**2 / (s**2).sum().clamp_min(1e-12)
    return {"top_sv_over_rms": s[0] / rms, "effective_rank": torch.exp(-(p * torch.log(p + 1e-12)).sum())}


def weight_features(tensors: Mapping[str, torch.Tensor], obs_dim: int, cell: str) -> dict[str, torch.Tensor]:
    """Named 0-d float64 tensors, differentiable in ``tensors`` (``cells.<i>.weight_ih`` etc., as in a state dict) of
    a network of ``cell`` layers: each layer class names its own features (``weight_features``).

    Recurrent cells (LSTM, peephole LSTM, GRU) give the per-gate statistics above (a GRU's gates: reset, update,
    new); a peephole LSTM adds the moments of each gate's peephole weights. A Transformer layer gives the moments
    and spectra of each linear map (input, qkv, out, mlp_in, mlp_out), the moments of their biases and of the
    position biases. The input-code norms read the first layer's input weights in every case."""
    layer = layer_class(cell)
    layers = sorted({int(k.split(".")[1]) for k in tensors if k.startswith("cells.")})
    feats: dict[str, torch.Tensor] = {}
    for tag, index in (("first", layers[0]), ("last", layers[-1])):
        w_in = layer.weight_features(tensors, f"cells.{index}.", tag, feats)
        if tag == "first" and w_in.shape[1] == obs_dim and obs_dim % NUM_CHANNELS == 0:
            per_code = w_in.reshape(w_in.shape[0], -1, NUM_CHANNELS).pow(2).sum((0, 1))  # (6,)
            per_code = _sqrt(per_code)
            per_code = per_code / (per_code.mean() + 1e-12)
            for code, value in zip(CELL_NAMES, per_code.unbind(0)):
                feats[f"input_codes/{code}"] = value
    return feats


def gated_layer_features(
    tensors: Mapping[str, torch.Tensor], prefix: str, tag: str, feats: dict[str, torch.Tensor]
) -> torch.Tensor:
    """The per-gate features of one LSTM/GRU layer into ``feats``; returns its input weights (float64)."""
    w_ih = tensors[prefix + "weight_ih"].double()
    w_hh = tensors[prefix + "weight_hh"].double()
    bias = tensors[prefix + "bias_ih"].double() + tensors[prefix + "bias_hh"].double()
    hidden = w_hh.shape[1]
    gates = GATES if w_ih.shape[0] == 4 * hidden else GRU_GATES
    for g, gate in enumerate(gates):
        rows = slice(g * hidden, (g + 1) * hidden)
        for block, w in (("ih", w_ih[rows]), ("hh", w_hh[rows]), ("bias", bias[rows])):
            for name, value in _moments(w).items():
                feats[f"gate_stats/{tag}.{gate}.{block}.{name}"] = value
            if block != "bias":
                for name, value in _spectral(w).items():
                    feats[f"spectral/{tag}.{gate}.{block}.{name}"] = value
    if prefix + "peephole" in tensors:
        peephole = tensors[prefix + "peephole"].double()
        for gate, row in zip(("input", "forget", "output"), peephole.unbind(0)):
            for name, value in _moments(row).items():
                feats[f"peephole/{tag}.{gate}.{name}"] = value
    return w_ih


def attention_layer_features(
    tensors: Mapping[str, torch.Tensor], prefix: str, tag: str, feats: dict[str, torch.Tensor]
) -> torch.Tensor:
    """The features of one windowed Transformer layer into ``feats``; returns its input projection (float64)."""
    for block in ATTENTION_BLOCKS:
        w = tensors[f"{prefix}{block}.weight"].double()
        for name, value in _moments(w).items():
            feats[f"gate_stats/{tag}.{block}.weight.{name}"] = value
        for name, value in _spectral(w).items():
            feats[f"spectral/{tag}.{block}.weight.{name}"] = value
        for name, value in _moments(tensors[f"{prefix}{block}.bias"].double()).items():
            feats[f"gate_stats/{tag}.{block}.bias.{name}"] = value
    for name, value in _moments(tensors[prefix + "position_bias"].double()).items():
        feats[f"gate_stats/{tag}.position_bias.{name}"] = value
    return tensors[prefix + "input.weight"].double()


def module_features(module: RecurrentActorCritic, obs_dim: int) -> dict[str, torch.Tensor]:
    """:func:`weight_features` of a module's parameters (a :class:`~seqtrojan.agent.network.RecurrentActorCritic`),
    differentiable in them."""
    return weight_features(dict(module.named_parameters()), obs_dim, module.cell)


def feature_vector(feats: dict[str, torch.Tensor]) -> tuple[torch.Tensor, tuple[str, ...]]:
    """(F,) the features in name order, and the names."""
    names = tuple(sorted(feats))
    return torch.stack([feats[n] for n in names]), names
