"""Sequence nets predicting the mid frame's deformed body-part positions from a token window.

Both nets share one forward signature, in canonical coordinates (the mid frame's rigid-model
frame, see `deformnet.tokens.canonicalize`):

    forward(rigid (B, W, K, 3), deformed (B, W, K, 3), observed (B, W, K) bool) -> (B, K, 3)

and share `encode(rigid, deformed, observed) -> (B, W, encode_dim) per-frame encoder outputs,
(B, K, P) interpolation prior`, the part `forward` feeds to its per-part output layer at the mid
frame (and what behavior heads read).

They predict the deformation offset relative to the mid rigid point (residual) with a zero-
initialised output layer, so an untrained net is the rigid baseline. The mid frame's deformed input
is masked inside (`deformnet.tokens.token_features`) whatever the caller passes.

Plain `nn.Module`s, named by their `_target_` (conf/net/*.yaml, a checkpoint's net_config) and
built from the allow-list `NETS` (`deformnet.deformation.build_net`); no Lightning here.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from deformnet.tokens import (
    NUM_FEATURES,
    OFFSET_SCALE,
    POS_SCALE,
    PRIOR_FEATURES,
    check_window,
    token_features,
)

__all__ = [
    "LSTMPredictor",
    "TransformerPredictor",
    "PartTransformer",
    "PartHead",
    "zero_linear",
    "rest_features",
    "is_part_agnostic",
    "sinusoidal_encoding",
    "NETS",
]


def zero_linear(d_in: int, d_out: int) -> nn.Linear:
    """A Linear layer with zero weight and bias (an output layer whose untrained net predicts
    zero offsets: the rigid baseline)."""
    layer = nn.Linear(d_in, d_out)
    nn.init.zeros_(layer.weight)
    nn.init.zeros_(layer.bias)
    return layer


class PartHead(nn.Module):
    """Per-part output layer: part i's offset from the window context and its own prior.

    h_i = W_i ctx + U [prior_i, e_i] (e_i a learned part embedding), then a shared MLP -> 3.
    The shared path lets all parts learn one use of their interpolation prior; the per-part
    context projection keeps a joint view of the window. The last layer (`out`) is zero-
    initialised, so an untrained head outputs zero offsets (the rigid baseline), or, with
    ``prior_residual``, the prior's linearly interpolated body-frame offset (the linear
    baseline: a net trained from scratch on little data starts from interpolation).
    """

    def __init__(
        self,
        ctx_dim: int,
        num_parts: int,
        hidden: int,
        d_part: int = 16,
        prior_residual: bool = False,
    ) -> None:
        super().__init__()
        self.num_parts, self.hidden = int(num_parts), int(hidden)
        self.prior_residual = bool(prior_residual)
        self.part_embedding = nn.Embedding(self.num_parts, d_part)
        self.ctx = nn.Linear(ctx_dim, self.num_parts * self.hidden)
        self.local = nn.Linear(PRIOR_FEATURES + d_part, self.hidden, bias=False)
        self.mlp = nn.Sequential(nn.GELU(), nn.Linear(self.hidden, self.hidden), nn.GELU())
        self.out = zero_linear(self.hidden, 3)

    def forward(self, ctx: Tensor, prior: Tensor) -> Tensor:
        """ctx (B, C), prior (B, K, P) -> offsets (B, K, 3) in units of offset_scale."""
        B = ctx.shape[0]
        emb = self.part_embedding.weight.to(prior.dtype).expand(B, -1, -1)
        h = self.ctx(ctx).reshape(B, self.num_parts, self.hidden)
        h = h + self.local(torch.cat((prior, emb), -1))
        out = self.out(self.mlp(h))
        if self.prior_residual:  # on top of the interpolation prior's offset (its first 3)
            out = out + prior[..., :3]
        return out


class _Base(nn.Module):
    """What every net shares: the window (half_window n, W = 2n + 1), the input scales, the
    token features of a window (`_features`) and the offset back to mm (`_finish`). num_parts:
    K (None for a part-agnostic net)."""

    def __init__(
        self, num_parts: int | None, half_window: int, pos_scale: float, offset_scale: float
    ) -> None:
        super().__init__()
        self.num_parts = None if num_parts is None else int(num_parts)
        self.half_window = int(half_window)
        self.window = 2 * self.half_window + 1
        self.pos_scale = float(pos_scale)
        self.offset_scale = float(offset_scale)

    def _check(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> None:
        check_window(rigid, deformed, observed, self.window, self.num_parts)

    def _features(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> tuple[Tensor, Tensor]:
        """Token features (B, W, K, F) and the interpolation prior (B, K, P)."""
        self._check(rigid, deformed, observed)
        feats, prior, _ = token_features(
            rigid, deformed, observed, self.half_window, self.pos_scale, self.offset_scale
        )
        return feats, prior

    def _finish(self, offset: Tensor, rigid: Tensor) -> Tensor:
        return rigid[:, self.half_window] + offset * self.offset_scale


class _FixedParts(_Base):
    """A net for one keypoint set of num_parts K >= 1 parts (by index)."""

    def __init__(
        self, num_parts: int, half_window: int, pos_scale: float, offset_scale: float
    ) -> None:
        if num_parts < 1 or half_window < 0:
            raise ValueError(
                f"need num_parts >= 1 and half_window >= 0, got {num_parts}, {half_window}"
            )
        super().__init__(num_parts, half_window, pos_scale, offset_scale)


class LSTMPredictor(_FixedParts):
    """Bidirectional LSTM over time; each frame's K tokens are embedded jointly; the output at the
    mid frame, with the interpolation prior of `token_features`, predicts the K offsets.

    num_parts K, half_window n (W = 2n + 1), hidden size per direction, layers, dropout;
    prior_residual: predict on top of the interpolation prior (`PartHead`).
    """

    def __init__(
        self,
        num_parts: int,
        half_window: int = 16,
        hidden: int = 64,
        layers: int = 2,
        embed: int = 64,
        dropout: float = 0.0,
        pos_scale: float = POS_SCALE,
        offset_scale: float = OFFSET_SCALE,
        prior_residual: bool = False,
    ) -> None:
        super().__init__(num_parts, half_window, pos_scale, offset_scale)
        K = self.num_parts
        self.embed = nn.Sequential(nn.Linear(K * NUM_FEATURES, embed), nn.GELU())
        self.lstm = nn.LSTM(
            embed,
            hidden,
            num_layers=layers,
            batch_first=True,
            bidirectional=True,
            dropout=dropout if layers > 1 else 0.0,
        )
        self.head = PartHead(2 * hidden + embed, K, 2 * hidden, prior_residual=prior_residual)
        self.encode_dim = 2 * hidden + embed  # per-frame outputs of `encode`

    def encode(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> tuple[Tensor, Tensor]:
        """The encoder's per-frame outputs (B, W, 2 hidden + embed) (the LSTM's output and the
        frame embedding) and the interpolation prior (B, K, P)."""
        feats, prior = self._features(rigid, deformed, observed)  # (B, W, K, F), (B, K, P)
        B, W = feats.shape[:2]
        e = self.embed(feats.reshape(B, W, -1))
        h, _ = self.lstm(e)
        return torch.cat((h, e), -1), prior

    def forward(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> Tensor:
        seq, prior = self.encode(rigid, deformed, observed)
        out = self.head(seq[:, self.half_window], prior)
        return self._finish(out, rigid)


def sinusoidal_encoding(length: int, dim: int, offset: int = 0) -> Tensor:
    """(length, dim) sinusoidal positional encoding of positions offset .. offset+length-1."""
    pos = torch.arange(length, dtype=torch.float64)[:, None] + offset
    i = torch.arange(0, dim, 2, dtype=torch.float64)
    freq = torch.exp(-math.log(10000.0) * i / dim)
    pe = torch.zeros(length, dim, dtype=torch.float64)
    pe[:, 0::2] = torch.sin(pos * freq)
    pe[:, 1::2] = torch.cos(pos * freq)[:, : dim // 2]
    return pe.float()


class TransformerPredictor(_FixedParts):
    """Transformer encoder over time.

    Each token (t, i) is embedded by a shared MLP from its features plus a learned embedding of the
    part identity i; a frame's K token embeddings are concatenated and projected to one frame
    vector (W sequence elements, cheap enough for CPU training), to which a sinusoidal positional
    encoding over time (relative to the mid frame) is added. The encoder output at the mid frame
    predicts the K deformation offsets.
    """

    def __init__(
        self,
        num_parts: int,
        half_window: int = 16,
        d_model: int = 64,
        heads: int = 4,
        layers: int = 2,
        ff: int = 128,
        d_part: int = 16,
        dropout: float = 0.0,
        pos_scale: float = POS_SCALE,
        offset_scale: float = OFFSET_SCALE,
        use_pos_enc: bool = True,
        prior_residual: bool = False,
    ) -> None:
        super().__init__(num_parts, half_window, pos_scale, offset_scale)
        K = self.num_parts
        self.use_pos_enc = bool(use_pos_enc)
        self.part_embedding = nn.Embedding(K, d_part)
        self.token_embed = nn.Sequential(
            nn.Linear(NUM_FEATURES + d_part, d_part), nn.GELU(), nn.Linear(d_part, d_part)
        )
        self.frame_embed = nn.Linear(K * d_part, d_model)
        pe = sinusoidal_encoding(self.window, d_model, offset=-self.half_window)
        self.register_buffer("pos_encoding", pe, persistent=False)
        layer = nn.TransformerEncoderLayer(
            d_model,
            heads,
            ff,
            dropout=dropout,
            batch_first=True,
            norm_first=True,
            activation="gelu",
        )
        self.encoder = nn.TransformerEncoder(layer, layers, enable_nested_tensor=False)
        self.norm = nn.LayerNorm(d_model)
        self.head = PartHead(d_model, K, 2 * d_model, prior_residual=prior_residual)
        self.encode_dim = d_model  # per-frame outputs of `encode`

    def encode(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> tuple[Tensor, Tensor]:
        """The encoder's per-frame outputs (B, W, d_model) (normalised) and the interpolation
        prior (B, K, P)."""
        feats, prior = self._features(rigid, deformed, observed)  # (B, W, K, F), (B, K, P)
        B, W, K, _ = feats.shape
        part = self.part_embedding.weight.to(feats.dtype).expand(B, W, K, -1)
        tok = self.token_embed(torch.cat((feats, part), -1))  # (B, W, K, d_part)
        x = self.frame_embed(tok.reshape(B, W, -1))  # (B, W, d_model)
        if self.use_pos_enc:
            x = x + self.pos_encoding.to(feats.dtype)[None]
        return self.norm(self.encoder(x)), prior

    def forward(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> Tensor:
        seq, prior = self.encode(rigid, deformed, observed)
        out = self.head(seq[:, self.half_window], prior)
        return self._finish(out, rigid)


REST_FREQS = (1.0, 2.0, 4.0)  # Fourier frequencies of the rest-coordinate features
REST_FEATURES = 5 + 6 * len(REST_FREQS)  # r (3), |r_x|, side, sin/cos of r at each frequency
SIDE_WIDTH = 0.1  # |r_x| (in body radii) over which the side feature goes from 0 to +-0.76


def rest_features(rest: Tensor) -> Tensor:
    """Where each part sits on the body, independent of its index or name.

    rest: (B, K, 3) the parts' rest-shape points in the body model's frame (X right, Y
    forward, Z up: the canonical mid frame's rigid points). Normalised by the body's size
    (centred on the parts' centroid, divided by their rms radius, so a small and a large body,
    or 8 and 34 parts of one, give comparable values), then: r (3); |r_x|, the distance from
    the mid-sagittal plane; side = tanh(r_x / SIDE_WIDTH) (-1 left, 0 on the midline, +1 right:
    the left/right symmetry feature, a mirror pair differing only in its sign); and sin, cos
    of r at the frequencies REST_FREQS (pi units). Returns (B, K, REST_FEATURES).
    """
    c = rest - rest.mean(-2, keepdim=True)
    radius = c.square().sum(-1).mean(-1).sqrt().clamp_min(1e-6)  # (B,)
    r = c / radius[:, None, None]
    side = torch.tanh(r[..., :1] / SIDE_WIDTH)
    ang = torch.cat([math.pi * f * r for f in REST_FREQS], -1)
    return torch.cat((r, r[..., :1].abs(), side, torch.sin(ang), torch.cos(ang)), -1)


class PartTransformer(_Base):
    """One net for any keypoint set: parts are identified by where they sit on the body.

    Each part's identity is an embedding of its rest-shape coordinates (`rest_features`: the
    canonical mid frame's rigid points, which in the body frame are the body model's points,
    normalised by the body's size, with a left/right symmetry feature), never a fixed index,
    so one set of weights runs on 8, 22, 34 parts or a skeleton it has never seen, and the
    output is equivariant to the order of the parts (permuting the inputs' parts permutes
    the outputs alike).

    Per part (shared weights): an MLP reads its whole window of token features
    (`deformnet.tokens.token_features`: rigid position, the observed offset in that frame's
    body frame, the observed flag; W x 7), its interpolation prior and its rest features, and
    adds the rest embedding: one token per part (B, K, d). ``layers`` transformer layers then
    attend across the parts (a part borrows from the parts near it on the body and from its
    mirror partner: their motion in the same window), and a per-part MLP of the result and the
    prior predicts the mid frame's offset (zero-initialised last layer: an untrained net is the
    rigid baseline, or with ``prior_residual`` the linear interpolation of the prior). Cheap:
    the attention is over K tokens, not K x W.

    num_parts: accepted for the config contract (every net is built with it) and ignored.
    """

    part_agnostic = True

    def __init__(
        self,
        num_parts: int | None = None,
        half_window: int = 12,
        d_model: int = 64,
        heads: int = 4,
        layers: int = 2,
        ff: int = 128,
        hidden: int = 128,
        dropout: float = 0.0,
        pos_scale: float = POS_SCALE,
        offset_scale: float = OFFSET_SCALE,
        prior_residual: bool = False,
    ) -> None:
        if half_window < 0 or layers < 0:
            raise ValueError(f"need half_window, layers >= 0, got {half_window}, {layers}")
        super().__init__(num_parts, half_window, pos_scale, offset_scale)  # num_parts: not used
        self.prior_residual = bool(prior_residual)
        d, h = int(d_model), int(hidden)
        self.window_mlp = nn.Sequential(
            nn.Linear(self.window * NUM_FEATURES + PRIOR_FEATURES + REST_FEATURES, h),
            nn.GELU(),
            nn.Linear(h, h),
            nn.GELU(),
            nn.Linear(h, d),
        )
        self.rest_embed = nn.Sequential(nn.Linear(REST_FEATURES, d), nn.GELU(), nn.Linear(d, d))
        self.token_embed = nn.Linear(NUM_FEATURES, d)  # per-frame tokens for `encode` only
        if layers:
            layer = nn.TransformerEncoderLayer(
                d, heads, ff, dropout=dropout, batch_first=True, norm_first=True,
                activation="gelu",
            )  # fmt: skip
            self.part_encoder: nn.Module = nn.TransformerEncoder(
                layer, layers, enable_nested_tensor=False
            )
        else:
            self.part_encoder = nn.Identity()
        self.norm = nn.LayerNorm(d)
        self.head = nn.Sequential(nn.Linear(d + PRIOR_FEATURES, h), nn.GELU())
        self.out = zero_linear(h, 3)
        self.encode_dim = d  # per-frame outputs of `encode`

    def _check(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> None:
        check_window(rigid, deformed, observed, self.window, rigid.shape[-2])  # any K

    def _part_features(self, rigid: Tensor, deformed: Tensor, observed: Tensor):
        """Token features (B, W, K, F), the prior (B, K, P), rest features (B, K, R)."""
        feats, prior = self._features(rigid, deformed, observed)
        return feats, prior, rest_features(rigid[:, self.half_window])

    def encode(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> tuple[Tensor, Tensor]:
        """Per-frame outputs (B, W, d_model) (the tokens' embeddings plus their parts' rest
        embeddings, averaged over the parts, normalised) and the interpolation prior (B, K, P)."""
        feats, prior, rest = self._part_features(rigid, deformed, observed)
        x = self.token_embed(feats) + self.rest_embed(rest)[:, None]  # (B, W, K, d)
        return self.norm(x.mean(2)), prior

    def forward(self, rigid: Tensor, deformed: Tensor, observed: Tensor) -> Tensor:
        feats, prior, rest = self._part_features(rigid, deformed, observed)
        B, W, K, F = feats.shape
        win = feats.permute(0, 2, 1, 3).reshape(B, K, W * F)
        x = self.window_mlp(torch.cat((win, prior, rest), -1)) + self.rest_embed(rest)
        h = self.norm(self.part_encoder(x))  # (B, K, d)
        out = self.out(self.head(torch.cat((h, prior), -1)))
        if self.prior_residual:  # on top of the interpolation prior's offset (its first 3)
            out = out + prior[..., :3]
        return self._finish(out, rigid)


def is_part_agnostic(net: nn.Module) -> bool:
    """Whether a net identifies parts by their rest coordinates (runs on any skeleton)."""
    return bool(getattr(net, "part_agnostic", False))


#: the nets a config or a checkpoint may name (its ``_target_``): `deformnet.deformation.build_net`
#: builds only these (a checkpoint is data: nothing else it names is imported or instantiated)
NETS: dict[str, type[nn.Module]] = {
    "deformnet.nets.LSTMPredictor": LSTMPredictor,
    "deformnet.nets.TransformerPredictor": TransformerPredictor,
    "deformnet.nets.PartTransformer": PartTransformer,
}
