"""The recurrent actor-critic: observation -> stacked sequence-model layers -> policy logits and value.

The layers are LSTM cells by default (the paper's network); ``cell`` picks another sequence model
(:mod:`seqtrojan.agent.cells`: peephole LSTM, GRU, windowed Transformer) with the same state contract.

Optional MLP parts (none by default: the paper's network) describe agents trained elsewhere and imported
(:mod:`seqtrojan.agent.imports`): ``encoder`` layers before the first LSTM layer, ``policy_mlp`` / ``value_mlp``
layers between the last LSTM layer and each head; each layer is a linear map followed by its activation.

The state always goes in and comes out (:class:`RecurrentState`); nothing is kept inside the module.
``step`` runs one time step for a batch and lets a caller-supplied intervention edit each layer's (h, c);
``unroll`` runs T steps with episode-start masks. Both compute exactly the same function (tested).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import NamedTuple, cast

import torch
from torch import nn

from seqtrojan.agent import fast_lstm
from seqtrojan.agent.cells import CellLayer, make_cell
from seqtrojan.agent.state import Intervention, LSTMState, RecurrentState
from seqtrojan.cell_types import cell_type
from seqtrojan.config import MAX_CONV_KERNEL, MAX_CONV_STRIDE
from seqtrojan.errors import ConfigError

BACKENDS = ("auto", "torch", "cpp")
ACTIVATIONS = {"tanh": torch.tanh, "relu": torch.relu}
"""the optional MLP layers' activation functions, by name (the names of :data:`seqtrojan.config.ACTIVATIONS`)"""


class StepOutput(NamedTuple):
    logits: torch.Tensor  # (B, A)
    value: torch.Tensor  # (B,)
    state: RecurrentState


class UnrollOutput(NamedTuple):
    logits: torch.Tensor  # (T, B, A)
    values: torch.Tensor  # (T, B)
    state: RecurrentState  # after the last step
    states: tuple[LSTMState, ...] | None  # per layer (h, c), each (T, B, H), when return_states=True


class RecurrentActorCritic(nn.Module):
    """Stacked LSTM cells (widths e.g. 64, 32) with a policy head and a value head on the last layer.

    Optionally (all empty by default) ``encoder`` MLP layers before the first cell, and ``policy_mlp`` /
    ``value_mlp`` MLP layers before each head. Their modules exist only when they have layers, and they are built
    and initialised after the default parts, so that a network without them is exactly the one earlier versions
    built from the same seed (same parameters, same state_dict).
    """

    def __init__(
        self,
        obs_dim: int,
        num_actions: int,
        lstm_sizes: Sequence[int] = (64, 32),
        forget_bias: float = 1.0,
        memory: bool = True,
        *,
        encoder: Sequence[int] = (),
        encoder_activation: str = "relu",
        policy_mlp: Sequence[int] = (),
        value_mlp: Sequence[int] = (),
        mlp_activation: str = "tanh",
        cell: str = "lstm",
        window: int = 8,
        heads: int = 1,
        conv: Sequence[int] = (),
        image: Sequence[int] | None = None,
        conv_kernels: Sequence[int] = (),
        conv_strides: Sequence[int] = (),
    ):
        super().__init__()
        self.conv_channels = tuple(int(c) for c in conv)
        """channels of the optional convolutional encoder's layers (each a square kernel, a stride, no padding, then
        ReLU), before the MLP encoder: for image observations (MiniGrid's view, MinAtar's and Atari's frames)"""
        self.conv_kernels, self.conv_strides = conv_geometry(self.conv_channels, conv_kernels, conv_strides)
        """each conv layer's kernel size and stride (by default 2 and 1: the field's usual MiniGrid CNN; the Nature
        CNN of Atari agents: 8, 4, 3 and 4, 2, 1)"""
        self.image = tuple(int(d) for d in image) if image is not None else None
        """(rows, cols, channels): how a flat observation is laid out as an image, for the conv encoder"""
        conv_out = _conv_output(obs_dim, self.conv_channels, self.image, self.conv_kernels, self.conv_strides)
        if cell_type(cell).windowed:
            if not (isinstance(window, int) and window >= 1):
                raise ConfigError(f"a {cell}'s window must be an integer >= 1, got {window!r}")
            if heads < 1 or any(w % heads for w in lstm_sizes):
                raise ConfigError(f"a {cell}'s layer widths {list(lstm_sizes)} must be divisible by heads={heads}")
        self.cell = cell
        """the sequence model of every layer (a name in :data:`seqtrojan.cell_types.CELL_TYPES`)"""
        self.window = int(window)
        """the Transformer's context: the current input and the window - 1 before it"""
        self.attention_heads = int(heads)
        for name, activation in (("encoder_activation", encoder_activation), ("mlp_activation", mlp_activation)):
            if activation not in ACTIVATIONS:
                raise ConfigError(f"{name} must be one of {tuple(ACTIVATIONS)}, got {activation!r}")
        self.memory = memory
        """False: the state is reset before every step (a memoryless baseline)"""
        self.obs_dim = obs_dim
        self.num_actions = num_actions
        self.lstm_sizes = tuple(int(w) for w in lstm_sizes)
        self.encoder_sizes = tuple(int(w) for w in encoder)
        self.policy_mlp_sizes = tuple(int(w) for w in policy_mlp)
        self.value_mlp_sizes = tuple(int(w) for w in value_mlp)
        self.encoder_activation = encoder_activation
        self.mlp_activation = mlp_activation
        features = conv_out if self.conv_channels else obs_dim  # what the MLP encoder (or the first layer) reads
        lstm_in = self.encoder_sizes[-1] if self.encoder_sizes else features
        last = self.lstm_sizes[-1]
        inputs = (lstm_in, *self.lstm_sizes[:-1])
        self.cells = nn.ModuleList(make_cell(cell, i, w, window, heads) for i, w in zip(inputs, self.lstm_sizes))
        self.policy_head = nn.Linear(self.policy_mlp_sizes[-1] if self.policy_mlp_sizes else last, num_actions)
        self.value_head = nn.Linear(self.value_mlp_sizes[-1] if self.value_mlp_sizes else last, 1)
        self._init_weights(forget_bias)
        # the optional parts, after everything above (a network without them draws the same random numbers)
        if self.conv_channels:
            assert self.image is not None  # _conv_output checked it
            chans = (self.image[2], *self.conv_channels)
            convs = [
                nn.Conv2d(a, b, k, stride=s)
                for (a, b), k, s in zip(itertools.pairwise(chans), self.conv_kernels, self.conv_strides)
            ]
            for conv_layer in convs:
                nn.init.orthogonal_(conv_layer.weight, gain=2**0.5)
                nn.init.zeros_(cast(torch.Tensor, conv_layer.bias))
            self.conv = nn.ModuleList(convs)
        for name, n_in, widths in (
            ("encoder", features, self.encoder_sizes),
            ("policy_mlp", last, self.policy_mlp_sizes),
            ("value_mlp", last, self.value_mlp_sizes),
        ):
            if widths:
                layers = nn.ModuleList(nn.Linear(i, w) for i, w in zip((n_in, *widths[:-1]), widths))
                for layer in cast("Sequence[nn.Linear]", layers):
                    nn.init.orthogonal_(layer.weight, gain=2**0.5)
                    nn.init.zeros_(layer.bias)
                self.add_module(name, layers)
        self.lstm_backend = "auto"
        """'auto' uses the fused C++ kernels (:mod:`seqtrojan.agent.fast_lstm`) on CPU where they build, 'torch'
        never, 'cpp' always (an error where unavailable). Both compute the same function. For the Transformer the
        kernels are its band attention, its fused bias + residual + norm and bias + ReLU passes and its one-call rollout
        step (:mod:`seqtrojan.agent.fast_attention`); its linear layers' products are PyTorch's (BLAS)."""
        self._weight_cache: dict = {}

    def set_lstm_backend(self, backend: str) -> None:
        if backend not in BACKENDS:
            raise ConfigError(f"lstm backend must be one of {BACKENDS}, got {backend!r}")
        self.lstm_backend = backend

    def _kernels(self, x: torch.Tensor) -> bool:
        """Whether the layers run on the fused C++ kernels for input ``x``."""
        if self.lstm_backend == "torch":
            return False
        ok = fast_lstm.usable(x)
        if not ok and self.lstm_backend == "cpp":
            raise ConfigError(f"the C++ LSTM backend is unavailable here: {fast_lstm.error()}")
        return ok

    @property
    def layers(self) -> Sequence[CellLayer]:
        """The stacked sequence-model layers (the ``cells`` module list, typed)."""
        return cast("Sequence[CellLayer]", self.cells)

    @property
    def c_widths(self) -> tuple[int, ...]:
        """Each layer's ``c`` width: its h width for the LSTMs, 0 for the GRU, the key-value cache for the
        Transformer."""
        return tuple(layer.c_width for layer in self.layers)

    def _init_weights(self, forget_bias: float) -> None:
        for layer in self.layers:
            layer.init_weights(forget_bias)
        nn.init.orthogonal_(self.policy_head.weight, gain=0.01)
        nn.init.zeros_(self.policy_head.bias)
        nn.init.orthogonal_(self.value_head.weight, gain=1.0)
        nn.init.zeros_(self.value_head.bias)

    # ------------------------------------------------------------------ optional MLP parts
    def _mlp(self, name: str, activation: str, x: torch.Tensor) -> torch.Tensor:
        """``x`` through the MLP layers ``name`` (each linear, then ``activation``); ``x`` itself when it has none."""
        layers = self._modules.get(name)
        if layers is None:
            return x
        act = ACTIVATIONS[activation]
        for layer in cast("Sequence[nn.Linear]", layers):
            x = act(layer(x))
        return x

    def encode(self, obs: torch.Tensor) -> torch.Tensor:
        """The first layer's input: ``obs`` (..., obs_dim) through the conv encoder and the MLP encoder where the
        network has them, else ``obs`` itself."""
        if self.conv_channels:
            assert self.image is not None
            rows, cols, chans = self.image
            x = obs.reshape(-1, rows, cols, chans).permute(0, 3, 1, 2)  # (N, C, rows, cols)
            for layer in cast("Sequence[nn.Conv2d]", self.conv):
                x = torch.relu(layer(x))
            obs = x.flatten(1).reshape(*obs.shape[:-1], -1)
        return self._mlp("encoder", self.encoder_activation, obs)

    def heads(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Logits (..., A) and values (...) from the last LSTM layer's h (..., H)."""
        logits = self.policy_head(self._mlp("policy_mlp", self.mlp_activation, x))
        values = self.value_head(self._mlp("value_mlp", self.mlp_activation, x)).squeeze(-1)
        return logits, values

    # ------------------------------------------------------------------ state
    def initial_state(self, batch: int, device: torch.device | str | None = None) -> RecurrentState:
        weight = self.policy_head.weight
        return RecurrentState.zeros(
            batch, self.lstm_sizes, device if device is not None else weight.device, weight.dtype, self.c_widths
        )

    # ------------------------------------------------------------------ one step
    def step(
        self,
        obs: torch.Tensor,
        state: RecurrentState,
        episode_start: torch.Tensor | None = None,
        t: torch.Tensor | None = None,
        intervention: Intervention | None = None,
    ) -> StepOutput:
        """One time step. ``obs`` (B, obs_dim); ``episode_start`` (B,) zeroes those envs' state first;
        ``t`` (B,) is the per-env episode step handed to the intervention."""
        if not self.memory:
            episode_start = torch.ones(obs.shape[0], dtype=torch.bool, device=obs.device)
        fast = not torch.is_grad_enabled() and self._kernels(obs)
        keep = None if episode_start is None else (~episode_start.bool()).to(obs.dtype)
        if intervention is None and fast and self.layers[0].fused_stack_step:
            ones = torch.ones(obs.shape[0], dtype=obs.dtype)
            x = self.encode(obs)
            new = fast_lstm.step_stack(
                self.cells, x, ones if keep is None else keep, list(state.layers), self._weight_cache
            )
            fast_layers = tuple(LSTMState(h, c) for h, c in new)
            return StepOutput(*self.heads(new[-1][0]), RecurrentState(fast_layers))
        x = self.encode(obs)
        layers = []
        for i, layer in enumerate(self.layers):
            s = layer.step(x, state.layers[i], keep, fast)
            if intervention is not None:
                s = intervention(i, t, s)
            layers.append(s)
            x = s.h
        return StepOutput(*self.heads(x), RecurrentState(tuple(layers)))

    # ------------------------------------------------------------------ T steps
    def unroll(
        self,
        obs: torch.Tensor,
        state: RecurrentState,
        episode_starts: torch.Tensor,
        intervention: Intervention | None = None,
        t: torch.Tensor | None = None,
        return_states: bool = False,
    ) -> UnrollOutput:
        """T steps from ``state``: ``obs`` (T, B, obs_dim), ``episode_starts`` (T, B).

        Without an intervention the layers are unrolled one after the other (each layer's input projection is
        one matrix product over all T), which is faster and exact; with one, steps run in time order so that
        the intervention sees every layer of step t before step t + 1. ``t`` (T, B) is the episode step.
        """
        if not self.memory:
            episode_starts = torch.ones(obs.shape[:2], dtype=torch.bool, device=obs.device)
        if intervention is not None:
            return self._unroll_stepwise(obs, state, episode_starts, intervention, t, return_states)
        keep = (~episode_starts.bool()).to(obs.dtype)  # (T, B)
        fast = self._kernels(obs)
        x = self.encode(obs)
        finals: list[LSTMState] = []
        sequences: list[LSTMState] = []  # filled when return_states
        for layer, s in zip(self.layers, state.layers):
            x, final, seq = layer.unroll(x, s, keep, return_states, fast)
            finals.append(final)
            if seq is not None:
                sequences.append(seq)
        if x.transpose(0, 1).is_contiguous() and not x.is_contiguous():  # a batch-major layer (the Transformer):
            logits, values = self.heads(x.transpose(0, 1))  # the heads read it as it lies, not a time-major copy
            logits, values = logits.transpose(0, 1).contiguous(), values.t().contiguous()
        else:
            logits, values = self.heads(x)
        return UnrollOutput(logits, values, RecurrentState(tuple(finals)), tuple(sequences) if return_states else None)

    def _unroll_stepwise(
        self,
        obs: torch.Tensor,
        state: RecurrentState,
        episode_starts: torch.Tensor,
        intervention: Intervention,
        t: torch.Tensor | None,
        return_states: bool,
    ) -> UnrollOutput:
        logits, values, hs, cs = [], [], [], []
        for k in range(obs.shape[0]):
            out = self.step(obs[k], state, episode_starts[k], None if t is None else t[k], intervention)
            state = out.state
            logits.append(out.logits)
            values.append(out.value)
            if return_states:
                hs.append([s.h for s in state.layers])
                cs.append([s.c for s in state.layers])
        states = None
        if return_states:
            states = tuple(
                LSTMState(torch.stack([h[i] for h in hs]), torch.stack([c[i] for c in cs]))
                for i in range(len(self.cells))
            )
        return UnrollOutput(torch.stack(logits), torch.stack(values), state, states)


DEFAULT_CONV_KERNEL = 2
"""a conv layer's kernel size when none is given (what every earlier version built)"""
DEFAULT_CONV_STRIDE = 1


def conv_geometry(
    channels: Sequence[int], kernels: Sequence[int] = (), strides: Sequence[int] = ()
) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """Each conv layer's (kernel, stride): ``kernels`` and ``strides`` one per layer, or empty for the defaults
    (2 and 1); anything else is refused in one line."""
    out = []
    for name, given, default, top in (("kernels", kernels, DEFAULT_CONV_KERNEL, MAX_CONV_KERNEL),
                                      ("strides", strides, DEFAULT_CONV_STRIDE, MAX_CONV_STRIDE)):  # fmt: skip
        values = tuple(given)
        if not values:
            out.append((default,) * len(channels))
            continue
        if len(values) != len(channels) or any(isinstance(v, bool) or not isinstance(v, int) for v in values):
            raise ConfigError(
                f"conv {name} {list(values)}: one integer per conv layer ({len(channels)} layers), or none for "
                f"{default} each"
            )
        if any(not 1 <= v <= top for v in values):
            raise ConfigError(f"conv {name} {list(values)} must each lie in [1, {top}]")
        out.append(values)
    return out[0], out[1]


def conv_output_side(side: int, kernels: Sequence[int], strides: Sequence[int]) -> int:
    """An image side after the conv layers (no padding: each gives ``(side - kernel) // stride + 1``); 0 when a
    kernel no longer fits."""
    for k, s in zip(kernels, strides):
        if side < k:
            return 0
        side = (side - k) // s + 1
    return side


def _conv_output(
    obs_dim: int,
    channels: Sequence[int],
    image: Sequence[int] | None,
    kernels: Sequence[int] = (),
    strides: Sequence[int] = (),
) -> int:
    """Features out of the conv encoder; checks the layout (each kernel must fit the image left by the layers
    before it)."""
    if not channels:
        return obs_dim
    if image is None or len(image) != 3 or any(d < 1 for d in image):
        raise ConfigError(f"a conv encoder needs the image layout (rows, cols, channels), got {image!r}")
    rows, cols, chans = image
    if rows * cols * chans != obs_dim:
        raise ConfigError(f"image {list(image)} holds {rows * cols * chans} numbers, but observations have {obs_dim}")
    kernels, strides = conv_geometry(channels, kernels, strides)
    out_rows, out_cols = (conv_output_side(n, kernels, strides) for n in (rows, cols))
    fits = bool(out_rows and out_cols) and all(c >= 1 for c in channels)
    if not fits and set(kernels) == {DEFAULT_CONV_KERNEL} and set(strides) == {DEFAULT_CONV_STRIDE}:
        raise ConfigError(
            f"conv channels {list(channels)}: each 2x2 layer shrinks the {rows}x{cols} image by one, so at most "
            f"{min(rows, cols) - 1} layers of >= 1 channel"
        )
    if not fits:
        raise ConfigError(
            f"conv layers of channels {list(channels)}, kernels {list(kernels)} and strides {list(strides)} do not "
            f"fit the {rows}x{cols} image (each kernel must fit what the layers before it leave; channels >= 1)"
        )
    return out_rows * out_cols * channels[-1]
