"""Transporter networks (Zeng et al. 2020, "Transporter Networks: Rearranging the Visual
World for Robotic Manipulation"), goal-conditioned (Seita et al. 2021, "Learning to
Rearrange Deformable Cables, Fabrics, and Bags with Goal-Conditioned Transporter
Networks"), trained by imitation on expert pick-and-place demonstrations.

**Input.** A top-down picture of the scene (:class:`dax_tasks.ObservationMode`,
the task's camera): the height map (``transporter``) or the RGB picture and the height map
(``transporter_rgb``; the object's texture tells a cloth's corners or a rope's ends apart,
which a height map cannot), with the goal's picture in the same mode stacked on the
channels (``goal_image``, default on). The macro tasks' goals are shapes, not places: their
distance compares the object with the goal moved onto the object's pose
(``aligned_goal``); with ``align_goal`` (default) the goal is pictured so, at every
step, which tells a fully convolutional network where the goal's parts lie relative to the
object it sees (without it the goal's picture is the same at every start). Heights are
divided by ``height_scale``.

**Pick (attention).** A fully convolutional network (a small U-Net, :class:`FCN`) gives a
logit per pixel of its output grid (half the picture's resolution); the pick is the pixel
of the largest, trained with the cross-entropy of a softmax over all pixels against the
demonstrated pick.

**Place (transport).** Two more FCNs give key and query features per pixel. The query
features around the pick, a ``crop`` x ``crop`` window sampled at ``n_rotations`` rotations
about the pick (bilinear), are cross-correlated with the key features of the whole scene:
``n_rotations`` logit maps. The tasks' macro actions have no orientation, so the rotation
is latent: the place is the pixel of the largest ``logsumexp`` over rotations, trained with
``-log sum_r p(r, place)`` (the rotation marginalised out).

**Where exactly, and how high.** At each pixel the attention network also regresses the
pick's offset from the pixel's centre (a pixel is 1.5 cm of the cloth tasks' view, half a
vertex spacing: a pick 1 cm off snaps to another vertex) and its height above the height
map; the key network the same for the place (squared errors against the demonstrated
actions, in output pixels and in ``height_scale``). Pixels map to table coordinates
through the camera (:meth:`dax_tasks.viz.Camera.to_table`); the chosen pick and place
become the task's pick-and-place (or push start and end) action.

**Training.** ``train_steps`` Adam steps on batches of ``batch_size`` demonstrated steps
(each step of each demonstration is a sample), every sample rotated about the picture's
centre by up to ``augment_rotation`` and shifted by up to ``augment_shift`` pixels, its
pick and place moved with it (the original's SE(2) augmentation, within the tasks' own
start randomisation: a cloth's corners look alike in a height map turned by 90°); samples
whose labels leave the picture are masked. Applies to the macro-action tasks only (the five
cloth tasks and Push-Rope).
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax.scipy.ndimage import map_coordinates

import dax_tasks
from dax_tasks.core.wrappers import rgb_as_float

from .. import nets
from ..actions import to_normalised
from ..checks import check_fields
from ..learner import Learner, Policy, UpdateMetrics, make_evaluate
from ..method import NotApplicable
from ..optim import guarded_update, make_optimiser
from . import demos

MACRO_KINDS = ("push", "pick_place")


@dataclasses.dataclass(frozen=True)
class TransporterConfig:
    """rgb: height map and RGB picture (``transporter_rgb``), else the height map only;
    image_size: picture side [pixels] (a multiple of 8); goal_image: the goal's picture as
    more input channels; align_goal: the goal pictured aligned to the object's current
    pose (the task's ``aligned_goal``; ignored without ``goal_image``); demos:
    demonstrations used (of the standard set's 10); width: channels of the FCNs' first
    layer; features: key/query feature channels; crop: side of the query crop
    [output-grid pixels, odd; the grid is half the picture's resolution]; n_rotations:
    crop rotations; train_steps, batch_size,
    learning_rate, max_grad_norm: the Adam training; augment_rotation [rad],
    augment_shift [pixels]: augmentation ranges; height_scale [m]: heights are divided by
    it; n_eval: evaluation rollouts."""

    rgb: bool = False
    image_size: int = 64
    goal_image: bool = True
    align_goal: bool = True
    demos: int = 10
    width: int = 16
    features: int = 16
    crop: int = 9
    n_rotations: int = 8
    train_steps: int = 1000
    batch_size: int = 8
    learning_rate: float = 1e-3
    max_grad_norm: float | None = 10.0
    augment_rotation: float = 0.1
    augment_shift: float = 3.0
    height_scale: float = 0.05
    n_eval: int = 20

    def __post_init__(self):
        check_fields(self, ints=("image_size", "demos", "width", "features", "crop",
                                 "n_rotations", "train_steps", "batch_size", "n_eval"),
                     positive=("learning_rate", "height_scale"),
                     non_negative=("augment_rotation", "augment_shift"),
                     optional_positive=("max_grad_norm",))
        if self.image_size % 8:
            raise ValueError(f"image_size must be a multiple of 8, got {self.image_size}")
        if self.crop % 2 == 0:
            raise ValueError(f"crop must be odd (centred on the pick), got {self.crop}")

    @property
    def pictures_aligned_goal(self) -> bool:
        """The goal's picture is drawn aligned to the object (``align_goal`` with a goal
        picture at all)."""
        return self.goal_image and self.align_goal

    @property
    def mode(self) -> str:
        """The observation mode (:class:`dax_tasks.ObservationMode`)."""
        return "rgbd" if self.rgb else "height"

    @property
    def image_modes(self) -> tuple:
        """The pictures a demonstration file must hold (dax-data's image datasets)."""
        return ("height", "rgb") if self.rgb else ("height",)

    @property
    def channels(self) -> int:
        return (4 if self.rgb else 1) * (2 if self.goal_image else 1)

    @property
    def height_channels(self) -> tuple:
        """The channels that are height maps [m] (the scene's first)."""
        per = 4 if self.rgb else 1
        return tuple(per * k + per - 1 for k in range(2 if self.goal_image else 1))


def check_task(env) -> None:
    """:class:`dax_algos.method.NotApplicable` unless ``env`` has macro actions."""
    if env.spec.action_kind not in MACRO_KINDS:
        raise NotApplicable(
            f"Transporter networks choose a pick and a place: they need a macro-action task "
            f"({', '.join(MACRO_KINDS)}); {env.spec.name} has {env.spec.action_kind} actions")


def train_env_steps(env, config) -> int:
    """0: the networks learn from the demonstrations, not from environment steps."""
    return 0


def observation_env(env, config: TransporterConfig) -> dax_tasks.ObservationMode:
    """The env seen through the pictures the networks take."""
    return dax_tasks.ObservationMode(env, config.mode, config.image_size,
                                     goal_image=config.goal_image,
                                     align_goal=config.pictures_aligned_goal)


# ----------------------------------------------------------------------------- networks

def _same_padding(size: int, k: int, stride: int) -> tuple:
    out = -(-size // stride)
    total = max((out - 1) * stride + k - size, 0)
    return total // 2, total - total // 2


def matmul_conv(lhs, rhs, window_strides, padding, lhs_dilation=None, rhs_dilation=None,
                dimension_numbers=None, feature_group_count=1, precision=None, **_):
    """``lax.conv_general_dilated`` for NHWC inputs and HWIO kernels without dilation or
    groups (what :class:`FCN`'s ``nnx.Conv`` layers ask for), computed as shifted slices
    and one matrix product: a convolution inside a loop body (the training's ``lax.scan``)
    hits an XLA:CPU performance bug (jax-ml/jax#12868) that slices and a dot product do
    not."""
    if any(d not in (None, 1) for d in (*(lhs_dilation or ()), *(rhs_dilation or ()))) \
            or feature_group_count != 1:
        raise NotImplementedError("matmul_conv: no dilation or feature groups")
    kh, kw, cin, cout = rhs.shape
    sh, sw = window_strides
    if isinstance(padding, str):
        pads = ([_same_padding(lhs.shape[-3], kh, sh), _same_padding(lhs.shape[-2], kw, sw)]
                if padding == "SAME" else [(0, 0), (0, 0)])
    else:
        pads = [tuple(p) for p in padding]
    x = jnp.pad(lhs, [(0, 0)] * (lhs.ndim - 3) + [pads[0], pads[1], (0, 0)])
    oh = (x.shape[-3] - kh) // sh + 1
    ow = (x.shape[-2] - kw) // sw + 1
    cols = [x[..., a:a + sh * (oh - 1) + 1:sh, b:b + sw * (ow - 1) + 1:sw, :]
            for a in range(kh) for b in range(kw)]
    patches = jnp.concatenate(cols, axis=-1) if len(cols) > 1 else cols[0]
    return patches @ rhs.reshape(kh * kw * cin, cout)


def _upsample(x):
    return jnp.repeat(jnp.repeat(x, 2, axis=-3), 2, axis=-2)


class FCN(nnx.Module):
    """A small U-Net, ``(S, S, cin) -> (S/2, S/2, cout)``: three stride-2 3x3 convolutions
    down to S/8 (a receptive field about the whole picture at S = 64), two
    nearest-neighbour upsamplings back to S/2, each fused with the same-resolution features
    on the way down. The output grid is half the picture's (no full-resolution layers
    after the first; a 64-pixel picture of the cloth tasks' view gives 1.5 cm output
    pixels, half a cloth's vertex spacing)."""

    def __init__(self, cin: int, cout: int, width: int, rngs: nnx.Rngs):
        w = width

        def conv(a, b, k=3, **kw):
            return nnx.Conv(a, b, (k, k), rngs=rngs, conv_general_dilated=matmul_conv, **kw)

        self.inc = conv(cin, w)
        self.down = nnx.List([conv(w, 2 * w, strides=2), conv(2 * w, 4 * w, strides=2),
                              conv(4 * w, 4 * w, strides=2)])
        self.mid = conv(4 * w, 4 * w)
        self.up = nnx.List([conv(8 * w, 4 * w), conv(6 * w, 2 * w)])
        self.out = conv(2 * w, cout, k=1)

    def __call__(self, x):
        h = nnx.relu(self.inc(x))
        skips = []
        for layer in self.down:
            h = nnx.relu(layer(h))
            skips.append(h)
        h = nnx.relu(self.mid(skips.pop()))
        for layer in self.up:
            h = nnx.relu(layer(jnp.concatenate([_upsample(h), skips.pop()], axis=-1)))
        return self.out(h)


#: Per-pixel regression outputs after the attention logit and after the key features: the
#: height offset and the sub-pixel (row, col) offset of a pick or place in that pixel.
N_REGRESS = 3


class TransporterNet(nnx.Module):
    """The attention (pick logit, then the pick's regression outputs), key (features, then
    the place's regression outputs) and query (features) networks of one picture
    ``(S, S, C)``."""

    def __init__(self, cin: int, width: int, features: int, rngs: nnx.Rngs):
        self.attention = FCN(cin, 1 + N_REGRESS, width, rngs)
        self.key = FCN(cin, features + N_REGRESS, width, rngs)
        self.query = FCN(cin, features, width, rngs)

    def __call__(self, x):
        return self.attention(x), self.key(x), self.query(x)


def network(env, config: TransporterConfig) -> nets.Network:
    """The three FCNs (:class:`TransporterNet`) for ``config``'s pictures (``env`` is not
    used)."""
    c = config
    return nets.Network(lambda rngs: TransporterNet(c.channels, c.width, c.features, rngs),
                        name=f"transporter {c.image_size}x{c.image_size}x{c.channels} "
                             f"width {c.width}, {c.features} features")


def preprocess(x, config: TransporterConfig):
    """Network input from an observation ``(..., S, S, C)``: heights divided by
    ``height_scale``."""
    scale = np.ones(config.channels, np.float32)
    scale[list(config.height_channels)] = 1.0 / config.height_scale
    return jnp.asarray(x, jnp.float32) * scale


def _rotation(theta):
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([jnp.stack([c, -s]), jnp.stack([s, c])])


def _sample(image, coords):
    """Bilinear samples of ``image`` (S, S, D) at continuous ``coords`` (..., 2) (row,
    col); zero outside."""
    rows, cols = coords[..., 0], coords[..., 1]
    return jax.vmap(lambda ch: map_coordinates(ch, [rows, cols], order=1, mode="constant",
                                               cval=0.0), in_axes=-1, out_axes=-1)(image)


def correlate(feat, kernels):
    """``(R, H, W)``: each of the kernels ``(R, c, c, D)`` cross-correlated with ``feat``
    ``(H, W, D)`` (zero padding, centred). Written as shifted slices and one contraction:
    a convolution with a different kernel per sample (under ``vmap``) is a grouped
    convolution, whose gradient XLA:CPU compiles poorly."""
    c = kernels.shape[1]
    h, w = feat.shape[:2]
    p = c // 2
    padded = jnp.pad(feat, ((p, p), (p, p), (0, 0)))
    shifted = jnp.stack([padded[a:a + h, b:b + w] for a in range(c) for b in range(c)])
    return jnp.einsum("ohwd,rod->rhw", shifted,
                      kernels.reshape(kernels.shape[0], c * c, -1))


def transport_logits(key_feat, query_feat, pick, config: TransporterConfig):
    """``(n_rotations, G, G)`` place logits on the output grid: the query features of a
    ``crop``-pixel window about ``pick`` (continuous output-grid (row, col)) turned by each
    rotation, cross-correlated with the key features."""
    c, n_rot = config.crop, config.n_rotations
    off = jnp.arange(c, dtype=jnp.float32) - (c - 1) / 2
    grid = jnp.stack(jnp.meshgrid(off, off, indexing="ij"), axis=-1)  # (c, c, 2)
    thetas = jnp.arange(n_rot, dtype=jnp.float32) * (2 * jnp.pi / n_rot)
    coords = jax.vmap(lambda th: pick + grid @ _rotation(th).T)(thetas)  # (R, c, c, 2)
    kernels = jax.vmap(lambda xy: _sample(query_feat, xy))(coords)       # (R, c, c, D)
    return correlate(key_feat, kernels)


def to_grid(pixel):
    """Continuous picture coordinates -> output-grid coordinates (half the resolution)."""
    return (pixel + 0.5) / 2 - 0.5


def grid_heights(height):
    """The height map (S, S) on the output grid (G, G): the largest of each 2 x 2 block."""
    g = height.shape[-1] // 2
    return jnp.max(height.reshape(*height.shape[:-2], g, 2, g, 2), axis=(-3, -1))


def _flat(pixel, size):
    rc = jnp.clip(jnp.round(pixel).astype(jnp.int32), 0, size - 1)
    return rc[0] * size + rc[1], rc


def _regression_error(out, rc, pixel, z):
    """Squared error of a pixel's regression outputs ``(dz, d_row, d_col)`` against the
    height offset ``z`` and the label's offset from the pixel's centre."""
    want = jnp.concatenate([z[None], pixel - rc.astype(jnp.float32)])
    return jnp.sum((out[rc[0], rc[1]] - want) ** 2)


def sample_loss(net, params, x, pick, place, z_pick, z_place, config):
    """The loss of one (augmented) sample, ``pick`` and ``place`` in picture coordinates:
    cross-entropy of the pick and of the place (the rotation marginalised) on the output
    grid, plus the squared errors of the regression outputs at the labelled pixels (height
    offsets in ``height_scale``, sub-pixel offsets in output pixels)."""
    g, d = config.image_size // 2, config.features
    att, key, query = net.apply(params, x)
    pick, place = to_grid(pick), to_grid(place)
    i_pick, rc_pick = _flat(pick, g)
    i_place, rc_place = _flat(place, g)
    lp = att[..., 0].ravel()
    ce_pick = jax.nn.logsumexp(lp) - lp[i_pick]
    logits = transport_logits(key[..., :d], query, pick, config)
    marg = jax.nn.logsumexp(logits, axis=0).ravel()
    ce_place = jax.nn.logsumexp(logits.ravel()) - marg[i_place]
    return (ce_pick + ce_place + _regression_error(att[..., 1:], rc_pick, pick, z_pick)
            + _regression_error(key[..., d:], rc_place, place, z_place))


def augment(key, x, pick, place, config):
    """``x`` (S, S, C) turned about the picture's centre by an angle uniform in
    ``±augment_rotation`` and shifted by up to ``augment_shift`` pixels (bilinear, edges
    repeated), with ``pick`` and ``place`` moved alike; ``valid`` is false if either left
    the picture."""
    size = config.image_size
    k_a, k_s = jax.random.split(key)
    angle = jax.random.uniform(k_a, (), minval=-1.0, maxval=1.0) * config.augment_rotation
    shift = jax.random.uniform(k_s, (2,), minval=-1.0, maxval=1.0) * config.augment_shift
    centre = jnp.full((2,), (size - 1) / 2, jnp.float32)
    rot = _rotation(angle)
    ij = jnp.stack(jnp.meshgrid(jnp.arange(size), jnp.arange(size), indexing="ij"), -1)
    src = (ij.astype(jnp.float32) - centre - shift) @ rot + centre  # R^T (q - c - t) + c
    warped = jax.vmap(lambda ch: map_coordinates(ch, [src[..., 0], src[..., 1]], order=1,
                                                 mode="nearest"),
                      in_axes=-1, out_axes=-1)(x)

    def move(p):
        return rot @ (p - centre) + centre + shift

    pick, place = move(pick), move(place)
    inside = lambda p: jnp.all((p > -0.5) & (p < size - 0.5))  # noqa: E731
    return warped, pick, place, inside(pick) & inside(place)


# ----------------------------------------------------------------------------- data

class TransporterData(NamedTuple):
    """The demonstrated steps (M of them): ``obs`` (M, S, S, C) the pictures as the policy
    sees them, ``pick`` / ``place`` (M, 2) continuous pixel coordinates (row, col) of the
    demonstrated action's pick and place, ``z_pick`` / ``z_place`` (M,) their heights above
    the height map at those pixels, in units of ``height_scale``."""

    obs: jnp.ndarray
    pick: jnp.ndarray
    place: jnp.ndarray
    z_pick: jnp.ndarray
    z_place: jnp.ndarray


def data_from_episodes(env, config: TransporterConfig, episodes) -> TransporterData:
    """The training samples of demonstration episodes (dax-data :class:`Episode` s with
    pictures): every step's picture (the goal's appended), exactly as
    :func:`observation_env` shows it, and its action's pick and place as pixels."""
    obs_env = observation_env(env, config)
    camera, size = obs_env.camera, config.image_size
    goal_picture = jax.jit(obs_env.goal_observation)
    goal = np.asarray(goal_picture()) if config.goal_image and not config.align_goal \
        else None
    z0 = np.float32(camera.window[4])
    obs, pick, place, z_pick, z_place = [], [], [], [], []
    for ep in episodes:
        steps = {int(k): i for i, k in enumerate(ep.point_steps)}
        for t in range(ep.length):
            height = ep.height[t][..., None]
            cur = (np.concatenate([np.asarray(rgb_as_float(ep.rgb[t])), height], axis=-1)
                   if config.rgb else height)
            if config.pictures_aligned_goal:
                if t not in steps:
                    raise ValueError(f"episode {ep.index}: no object points at step {t} "
                                     f"(points at steps {list(steps)}): align_goal needs "
                                     f"them at every step")
                goal = np.asarray(goal_picture(None, jnp.asarray(ep.points[steps[t]])))
            obs.append(np.concatenate([cur, goal], axis=-1) if goal is not None else cur)
            a = np.asarray(ep.actions[t], np.float32)
            hg = np.asarray(grid_heights(ep.height[t]))
            for xyz, pixels, heights in ((a[:3], pick, z_pick), (a[3:6], place, z_place)):
                px = np.asarray(camera.to_pixel(xyz[:2], size))
                rc = np.clip(np.round(np.asarray(to_grid(px))).astype(int), 0, size // 2 - 1)
                pixels.append(px)
                heights.append((xyz[2] - z0 - hg[rc[0], rc[1]]) / config.height_scale)
    return TransporterData(*(jnp.asarray(np.stack(v), jnp.float32)
                             for v in (obs, pick, place, z_pick, z_place)))


def load_data(env, config: TransporterConfig, path) -> TransporterData:
    """:func:`data_from_episodes` of the first ``config.demos`` episodes of the
    demonstration file ``path``, checked against ``env`` (:func:`demos.load_episodes`)."""
    check_task(env)
    camera = observation_env(env, config).camera
    episodes = demos.load_episodes(path, env, config.demos, config.image_modes,
                                   config.image_size, camera)
    return data_from_episodes(env, config, episodes)


def demo_spec(config: TransporterConfig) -> demos.DemoSpec:
    """dax-data's standard ``transporter`` set with pictures of ``image_size`` pixels, read
    by :func:`load_data`."""
    return demos.DemoSpec("transporter", lambda env, path: load_data(env, config, path),
                          config.image_size)


# ----------------------------------------------------------------------------- training

def fit(key, data: TransporterData, config: TransporterConfig):
    """``(params, metrics)``: the networks trained on ``data`` (pure; jit it). ``metrics``
    has one :class:`dax_algos.learner.UpdateMetrics` entry per Adam step (no environment steps: the
    training reads demonstrations only)."""
    net = network(None, config)
    opt = make_optimiser(config.learning_rate, config.max_grad_norm)
    m = data.obs.shape[0]

    def batch_loss(params, key):
        k_idx, k_aug = jax.random.split(key)
        idx = jax.random.randint(k_idx, (config.batch_size,), 0, m)
        x, pick, place, valid = jax.vmap(lambda k, *a: augment(k, *a, config))(
            jax.random.split(k_aug, config.batch_size), data.obs[idx], data.pick[idx],
            data.place[idx])
        losses = jax.vmap(lambda *a: sample_loss(net, params, *a, config))(
            preprocess(x, config), pick, place, data.z_pick[idx], data.z_place[idx])
        w = valid.astype(jnp.float32)
        return jnp.sum(losses * w) / jnp.maximum(jnp.sum(w), 1.0)

    grad_fn = jax.value_and_grad(batch_loss)

    def update(carry, key):
        params, opt_state = carry
        loss, grads = grad_fn(params, key)
        params, opt_state, gnorm, bad = guarded_update(opt, grads, opt_state, params, False)
        metrics = UpdateMetrics(
            env_steps=jnp.zeros((), jnp.int32), score=jnp.asarray(jnp.nan, jnp.float32),
            episode_return=jnp.asarray(jnp.nan, jnp.float32), grad_norm=gnorm,
            nonfinite=bad.astype(jnp.int32), grad_steps=jnp.ones((), jnp.int32), loss=loss)
        return (params, opt_state), metrics

    k_init, k_run = jax.random.split(key)
    params = net.init(k_init)
    (params, _), metrics = jax.lax.scan(update, (params, opt.init(params)),
                                        jax.random.split(k_run, config.train_steps))
    return params, metrics


def predict(net, params, obs, config: TransporterConfig):
    """``(pick, place, dz_pick, dz_place)`` for one observation ``(S, S, C)``: the pick and
    place as continuous output-grid coordinates (row, col; the grid has half the picture's
    resolution): the chosen pixel moved by its predicted sub-pixel offset (within the
    pixel); and the predicted height offsets [m]."""
    g, d = config.image_size // 2, config.features
    att, key, query = net.apply(params, preprocess(obs, config))

    def refine(out, k):
        rc = jnp.stack([k // g, k % g])
        return rc + jnp.clip(out[rc[0], rc[1], 1:], -0.5, 0.5), out[rc[0], rc[1], 0]

    pick, dz_pick = refine(att[..., 1:], jnp.argmax(att[..., 0].ravel()))
    logits = transport_logits(key[..., :d], query, pick, config)
    place, dz_place = refine(key[..., d:], jnp.argmax(jax.nn.logsumexp(logits, 0).ravel()))
    return pick, place, dz_pick * config.height_scale, dz_place * config.height_scale


def make_act(env, config: TransporterConfig):
    """``act(policy, obs) -> z``: the pick and place the networks choose in the observation
    ``obs`` (the picture of :func:`observation_env`), as the task's normalised action: each
    output pixel's centre on the table (the camera), at the height map's (largest) height
    there plus the predicted offset."""
    check_task(env)
    net = network(env, config)
    camera = observation_env(env, config).camera
    g, z0, hc = config.image_size // 2, camera.window[4], config.height_channels[0]

    def act(policy: Policy, obs):
        pick, place, dz_pick, dz_place = predict(net, policy.params, obs, config)
        heights = grid_heights(obs[..., hc])

        def point(pixel, dz):
            rc = jnp.clip(jnp.round(pixel).astype(jnp.int32), 0, g - 1)
            xy = camera.to_table(pixel, g)
            return jnp.concatenate([xy, (z0 + heights[rc[0], rc[1]] + dz)[None]])

        action = jnp.concatenate([point(pick, dz_pick), point(place, dz_place)])
        return to_normalised(env, action)

    return act


def make_train(env, config: TransporterConfig):
    """``train(key, params, data) -> (Policy, UpdateMetrics)`` (``params``,
    the env's, are not used: training reads the demonstrations only)."""
    check_task(env)

    def train(key, params, data):
        net_params, metrics = fit(key, data, config)
        return Policy(net_params, None), metrics

    return train


def make_evaluate_on_pictures(env, config: TransporterConfig, act,
                              per_rollout: bool = False):
    """:attr:`dax_algos.learner.Learner.make_evaluate` of Transporter networks: the
    evaluation rollouts of ``act`` on the pictures it sees (:func:`observation_env`; see
    :func:`dax_algos.learner.make_evaluate` for ``per_rollout``)."""
    return make_evaluate(observation_env(env, config), act, config.n_eval,
                         inputs=lambda obs, t: obs, per_rollout=per_rollout)


LEARNER = Learner(make_train=make_train, make_act=make_act, network=network,
                  train_env_steps=train_env_steps, make_evaluate=make_evaluate_on_pictures,
                  normalises_inputs=False,
                  demo_spec=demo_spec)
