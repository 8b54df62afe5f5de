"""The recurrent state, as a value: per-layer (h, c), passed into and out of every step, never kept inside a module.

Every sequence model uses this layout (:mod:`seqtrojan.agent.cells`): for an LSTM ``c`` is its cell state, for a
GRU it has width 0, for the windowed Transformer it is the stored window of recent layer inputs.

Analysis, interventions and the online defense all read and edit this structure between steps.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple, Protocol

import torch


class LSTMState(NamedTuple):
    h: torch.Tensor  # (batch, hidden)
    c: torch.Tensor  # (batch, hidden)


class RecurrentState(NamedTuple):
    layers: tuple[LSTMState, ...]  # one per layer, e.g. widths (64, 32)

    @staticmethod
    def zeros(
        batch: int,
        widths: Sequence[int],
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        c_widths: Sequence[int] | None = None,
    ) -> RecurrentState:
        """All-zero state; ``c_widths`` (default: the h widths, an LSTM's) sizes each layer's ``c``."""

        def z(w: int) -> torch.Tensor:
            return torch.zeros(batch, w, device=device, dtype=dtype)

        cw = widths if c_widths is None else c_widths
        return RecurrentState(tuple(LSTMState(z(w), z(v)) for w, v in zip(widths, cw, strict=True)))

    def mask(self, episode_start: torch.Tensor) -> RecurrentState:
        """Zero the state of the envs where ``episode_start`` (batch,) is true."""
        keep = (~episode_start.bool()).to(self.layers[0].h.dtype).unsqueeze(-1)  # (batch, 1)
        return RecurrentState(tuple(LSTMState(s.h * keep, s.c * keep) for s in self.layers))

    def detach(self) -> RecurrentState:
        return RecurrentState(tuple(LSTMState(s.h.detach(), s.c.detach()) for s in self.layers))

    def clone(self) -> RecurrentState:
        return RecurrentState(tuple(LSTMState(s.h.clone(), s.c.clone()) for s in self.layers))

    # Replaces tuple.index (a position lookup, meaningless for a state) with batch indexing, on purpose.
    def index(self, idx: torch.Tensor | slice) -> RecurrentState:  # type: ignore[override]
        """The state of a subset of the batch."""
        return RecurrentState(tuple(LSTMState(s.h[idx], s.c[idx]) for s in self.layers))

    @property
    def widths(self) -> tuple[int, ...]:
        return tuple(s.h.shape[-1] for s in self.layers)

    @property
    def c_widths(self) -> tuple[int, ...]:
        return tuple(s.c.shape[-1] for s in self.layers)


SUMMARY_NAMES = ("h_abs", "h_saturated", "h_spread")
"""the per-layer summaries of :func:`state_summaries`, in order"""


def state_summaries(hs: Sequence[torch.Tensor], saturation: float = 0.9, softness: float | None = None) -> torch.Tensor:
    """(..., 3 * layers) from each layer's h (..., H): the mean |h|, the share of units with |h| above ``saturation``
    and the spread of h across units (:data:`SUMMARY_NAMES`), what the query-response detector reads of each step's
    state. With ``softness`` the share counts each unit by a sigmoid of that width instead of a step, so that it has
    a gradient (the ``response_mimicry`` attacker)."""
    out = []
    for h in hs:
        magnitude = h.abs()
        out.append(magnitude.mean(-1))
        if softness is None:
            out.append((magnitude > saturation).to(h.dtype).mean(-1))
        else:
            out.append(torch.sigmoid((magnitude - saturation) / softness).mean(-1))
        out.append(h.std(-1) if h.shape[-1] > 1 else torch.zeros_like(h[..., 0]))
    return torch.stack(out, -1)


class Intervention(Protocol):
    """Called after each layer's cell update with the per-env episode step ``t`` (batch,), or None where the
    caller does not track it; returns the state the next layer and the next step will see. Used to edit units
    (analysis) and to reset states (online defense)."""

    def __call__(self, layer: int, t: torch.Tensor | None, state: LSTMState) -> LSTMState: ...
