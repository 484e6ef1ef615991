"""Synthesis with a trained generator: prediction, completion between keyframes, diverse samples.

All functions take and return numpy arrays: scaled features (the model's space, ``[-0.95, 0.95]``).
They run the generator through ``model.engine``, a ``meshseq.torch_net.TorchNet`` or a
``meshseq.numpy_net.NumpyNet`` (the same interface: numpy in and out, states ``(h, c)`` of
``(K, B, L)`` float32 arrays), so this module imports no torch. Shapes: V vertices, 9 channels, U
given frames.

- ``predict``: feed U >= 1 given frames (warm-up: the state takes in frames 0..U-2 with the
  prediction discarded), then roll out free from frame U-1.
- ``complete``: forward chain from key a and backward chain from key b (initial states +0.1 and
  -0.1, or random ones for diversity: ``uniform_states``, the same draws as torch's generator of
  the seed), joined (``JOINS``): ``stitch``, the paper's, where they
  agree best (method.md 3, **decision**: at ``argmin_i ||S^f_i - S^b_{n+1-i}||`` over inner
  frames, with a short linear blend), ``corrected`` (``corrected_crossfade``), or ``anchored``
  (the default: the corrected join drawn toward the straight line between the keys as far as the
  chains miss the far key, ``reach_weights``).
- ``complete_cma``: the optimisation baseline: the initial state of the forward chain optimised
  by CMA-ES so that the roll-out ends at key b.
- ``assemble_vertices``: features -> vertices that pass exactly through given frames (keys).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from meshseq import novelty
from meshseq.acap.parts import PLACEMENT_CHANNELS as PLACEMENT
from meshseq.errors import MeshseqError


def _frames(x) -> np.ndarray:
    return np.asarray(x, dtype=np.float32)


# --------------------------------------------------------------------------------------------
# prediction


#: Bound of the scaled features during free roll-outs: the training frames fill [-0.95, 0.95];
#: a little head-room lets a motion go slightly beyond them, never far (no explosion).
FEATURE_BOUND = 1.0


#: How a prediction sets its pace (``predict``): ``given`` slows the roll-out to the given frames'
#: pace where they move slower than the training frames nearest them did (``novelty.training_pace``;
#: a model stored without its training frames' latent steps: ``warm-up``); ``warm-up`` compares the
#: given steps with the steps the model predicted for them while warming up (``pace_factor``);
#: ``model`` keeps the model's own (the paper's roll-out).
PACES = ("given", "warm-up", "model")


def _rms(d: np.ndarray) -> np.ndarray:
    """``(B, V, C)`` -> ``(B,)``: RMS over vertices and channels."""
    return np.sqrt(np.square(d).mean((-2, -1)))


def pace_factor(given_steps: np.ndarray, expected_steps: np.ndarray) -> np.ndarray:
    """``(B, U-1)`` RMS sizes of the given frames' steps and of the steps the model predicted for
    the same transitions during its warm-up -> ``(B,)`` factor in [0, 1] on every generated step.

    The ratio compares the given motion with what the model expects at this phase of the motion
    (at the turn of a swing both are small), so a motion held still or slowing down gives a small
    factor and a motion at the model's pace gives 1. The roll-out is never sped up.
    """
    return np.minimum(given_steps.mean(1) / np.maximum(expected_steps.mean(1), 1e-12), 1.0)


#: A frame's share of the difference between the given velocity and the model's first step, which
#: fades into the model's own motion (``carried_steps``), chosen on the body set: a run's own
#: (``meshseq.carry``) where training stored one. 0: the model's steps as they are (the paper's).
CARRY = 0.6


def carried_steps(given: np.ndarray, generated: np.ndarray, carry: float = CARRY) -> np.ndarray:
    """``generated`` ``(B, n, V, C)`` with the given frames' velocity carried into its first steps:
    step t (from 1) becomes ``s_t + carry**t (v - s_1)``, ``s_t`` the generated steps and ``v`` the
    given frames' last step ``(B, U, V, C)``; unchanged with one given frame (no velocity).

    The model's first steps do not continue the given motion (on its own training frames the first
    generated step is at a cosine of about 0.1-0.2 with the true one, the given step at 0.9-1.0):
    the carried steps start at the given velocity and fade into the model's own, whose later steps
    (and so the rhythm of a fast periodic motion) are kept. A prefix of the roll-out is carried the
    same however many frames follow it.
    """
    x = np.asarray(given)
    if carry <= 0 or generated.shape[1] == 0 or x.shape[1] < 2:
        return generated
    steps = np.diff(np.concatenate([x[:, -1:], generated], axis=1), axis=1)
    miss = (x[:, -1] - x[:, -2]) - steps[:, 0]  # (B, V, C)
    fade = (carry ** np.arange(1, generated.shape[1] + 1)).astype(generated.dtype)  # (n,)
    return x[:, -1:] + np.cumsum(steps + fade[None, :, None, None] * miss[:, None], axis=1)


def continued_placement(given: np.ndarray, generated: np.ndarray) -> np.ndarray:
    """``generated`` ``(B, n, V, 12)`` with its placement channels moved, whole, so that the first
    generated frame continues the given frames ``(B, U, V, 12)``: the last given placement plus the
    given frames' last step (none with one given frame). The roll-out's later changes are kept.

    A part's place depends on the body it sits on; on a subject the model has not seen, the first
    step jumps toward where the training subjects carry it. Moving the whole trajectory removes
    that jump and keeps the motion the model predicts.
    """
    last = given[:, -1, :, PLACEMENT]
    step = last - given[:, -2, :, PLACEMENT] if given.shape[1] > 1 else 0.0
    out = generated.copy()
    out[..., PLACEMENT] += (last + step - generated[:, 0, :, PLACEMENT])[:, None]
    return out


def predict(model, given, n_frames: int, state=None, sample: bool = False,
            bound: float | None = FEATURE_BOUND, pace: str = "given",
            continue_placement: bool | None = None, guard: bool = True, carry: float | None = None) -> np.ndarray:
    """Generate ``n_frames`` frames after the given ones.

    Args:
        model: ``meshseq.api.Model``.
        given: ``(U, V, 9)`` or batched ``(B, U, V, 9)`` scaled features, U >= 1.
        n_frames: frames to generate (any number; the roll-out is free-running).
        state: initial ``(h, c)``; default the forward chain's +0.1.
        sample: draw the VAE latent instead of taking its mean (the torch model only).
        bound: clamp every generated frame to ``[-bound, bound]`` (the training data fill
            ``[-0.95, 0.95]``), so long roll-outs stay within the data's range; None: no clamp.
        pace: ``given`` (default): with U >= 2, every generated step is scaled by the given
            frames' pace over the pace of the training frames nearest them
            (``novelty.training_pace``: a pose held still stays still, a slowing motion stays
            slow); ``warm-up``: over the steps the model predicted for them (``pace_factor``; also
            ``given``'s rule for a model stored without its training frames' latent steps);
            ``model``: the roll-out as trained. One given frame says nothing of the pace.
        continue_placement: on a mesh of several parts (12 channels), ``continued_placement``
            (no effect on 9 channels); False: the placement channels as rolled out; None (default):
            for a model whose channels measure the parts from the mesh's centroid (``model.placement``
            ``centroid``), not for one that measures them from their anchors (their first step
            does not jump: method.md, "Meshes of several parts").
        guard: blend the roll-out towards ``novelty.fallback`` where the given frames are unlike
            the training frames or, with U >= 2, head where no training frame near them went
            (``novelty_weights``); no effect for a model stored without a novelty reference.
            False: the roll-out as it is (the paper's).
        carry: with U >= 2 the generated steps start from the given frames' velocity, its
            difference from the model's first step fading by this share a frame (``carried_steps``);
            None (default): the model's own (``model.carry``, fitted on its training frames:
            ``meshseq.carry``); 0: the model's steps as they are (the paper's).
    Returns:
        ``(n_frames, V, 9)`` (or ``(B, n_frames, V, 9)``) generated scaled features.
    """
    if pace not in PACES:
        raise MeshseqError(f"unknown pace {pace!r}; expected one of {', '.join(PACES)}")
    if carry is None:
        carry = getattr(model, "carry", CARRY)
    if not 0.0 <= carry < 1.0:
        raise MeshseqError(f"carry {carry!r}: expected a share in [0, 1) (0: the model's steps as they are)")
    x = _frames(given)
    single = x.ndim == 3
    if single:
        x = x[None]
    bsz, u = x.shape[:2]
    if u < 1:
        raise MeshseqError("prediction needs at least one given frame")
    net = model.engine
    if state is None:
        state = net.initial_state(bsz, 0)
    out = np.empty((bsz, int(n_frames)) + x.shape[2:], dtype=np.float32)
    state, expected = _warm_up(net, state, x, sample)
    latents = None
    if getattr(model, "novelty", None) is not None and (guard or pace == "given" and u > 1):
        latents = model.encode(x)
    factor = roll_out_pace(model, x, expected, pace, latents)
    cur = x[:, -1]
    for t in range(int(n_frames)):  # free-running; the time loop is the only Python loop
        prev = cur
        state, cur = net.step(state, cur, n_forward=bsz, sample=sample)
        if factor is not None:
            cur = prev + factor * (cur - prev)
        if bound is not None:
            cur = np.clip(cur, -bound, bound)
        out[:, t] = cur
    if carry > 0:
        out = carried_steps(x, out, carry)
        if bound is not None:
            np.clip(out, -bound, bound, out=out)
    if guard:
        weight = novelty_weights(model, x, latents)
        if weight is not None:
            out = novelty.guarded(out, x, weight)
            if bound is not None:
                np.clip(out, -bound, bound, out=out)
    if continue_placement is None:
        continue_placement = getattr(model, "placement", "centroid") == "centroid"
    if continue_placement and x.shape[-1] == 12 and n_frames > 0:
        out = continued_placement(x, out)
        if bound is not None:
            np.clip(out, -bound, bound, out=out)
    return out[0] if single else out


def roll_out_pace(model, x: np.ndarray, expected: np.ndarray, pace: str, latents: np.ndarray | None):
    """The factor ``(B, 1, 1)`` on every generated step after given frames ``x`` ``(B, U, V, C)``
    (``expected``: ``_warm_up``'s, ``latents``: their latent means ``(B, U, L)`` or None), or None
    for the model's own pace (``pace`` ``model``, or one given frame, which says nothing of it)."""
    if pace == "model" or x.shape[1] < 2:
        return None
    reference = getattr(model, "novelty", None)
    if pace == "given" and latents is not None and reference.steps is not None:
        factor = novelty.training_pace(latents, reference)
    else:  # warm-up, or a model stored without its training frames' latent steps
        factor = pace_factor(_rms(x[:, 1:] - x[:, :-1]), expected)
    return factor[:, None, None].astype(x.dtype)


def _warm_up(net, state, x: np.ndarray, sample: bool = False):
    """Feed frames ``x`` ``(B, U, V, C)`` but the last to the forward chains from ``state``:
    ``(state', expected)``, ``expected`` ``(B, U-1)`` the RMS size of the step the model predicted
    from each (what ``pace_factor`` compares the given steps with)."""
    expected = []
    for i in range(x.shape[1] - 1):
        state, guess = net.step(state, x[:, i], n_forward=x.shape[0], sample=sample)
        expected.append(_rms(guess - x[:, i]))
    return state, (np.stack(expected, 1) if expected else np.zeros((x.shape[0], 0), np.float32))


def novelty_weights(model, given: np.ndarray, latents: np.ndarray | None = None) -> np.ndarray | None:
    """The model's share ``(B,)`` of predictions after given frames ``(B, U, V, C)``: the guard
    weight of the most novel given frame, and with U >= 2 at most the direction weight of the last
    latent step (``meshseq.novelty``; a reference stored without training steps: the pose alone);
    None for a model without a novelty reference. ``latents``: the given frames' latent means
    ``(B, U, L)`` where already encoded."""
    reference = getattr(model, "novelty", None)
    if reference is None:
        return None
    z = latents if latents is not None else model.encode(given)
    weight = novelty.guard_weight(novelty.novelty(z, reference).max(axis=1))
    if z.shape[1] > 1 and reference.steps is not None:
        weight = np.minimum(weight, novelty.heading_weight(z, reference))
    return weight


# --------------------------------------------------------------------------------------------
# completion


@dataclass
class Completion:
    """Completed frames between two keys (both included) and how they were stitched.

    ``frames``: ``(S, n, V, 9)`` scaled features for S samples, ``frames[:, 0]`` = key a and
    ``frames[:, -1]`` = key b exactly; ``stitch``: ``(S,)`` frame index where the chains met;
    ``gap``: ``(S,)`` feature distance between the chains there (RMS per entry); ``line_share``:
    ``(S,)`` how much of each sample the anchored join took from the line between the keys
    (``line_shares``; None for the other joins).
    """

    frames: np.ndarray
    stitch: np.ndarray
    gap: np.ndarray
    evaluations: int = 0  # roll-outs an optimiser used (CMA-ES); 0 for the chains
    line_share: np.ndarray | None = None


def uniform_states(shape: tuple[int, ...], seed: int | None, count: int = 2) -> list[np.ndarray]:
    """``count`` float32 arrays of ``shape`` from U(-0.1, 0.1), drawn one after the other from one
    generator: for an int ``seed`` exactly what ``torch.rand(shape, generator=torch.Generator()
    .manual_seed(seed)) * 0.2 - 0.1`` gives for each (torch's CPU generator is MT19937 seeded as
    numpy's legacy seeding, and ``torch.rand`` keeps 24 bits of each 32-bit draw); None: unseeded."""
    bits = np.random.MT19937()  # (seeded from the OS)
    if seed is not None:
        bits._legacy_seeding(int(seed) & 0xFFFFFFFF)
    n = int(np.prod(shape))
    raw = bits.random_raw(count * n) & np.uint64(2**24 - 1)
    u = (raw.astype(np.float32) * np.float32(2.0**-24)).reshape((count,) + tuple(shape))
    return [a * np.float32(0.2) - np.float32(0.1) for a in u]


def chain_states(model, samples: int, random_state: bool, seed: int | None = None):
    """Initial states ``(h, c)`` ``(K, 2 samples, L)`` for ``samples`` forward chains followed by
    ``samples`` backward chains: the trained ones, or ``uniform_states`` of ``seed``."""
    h, c = model.engine.initial_state(samples, samples)
    if random_state:
        h, c = uniform_states(h.shape, seed)
    return h, c


def join_chain_states(states: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Several groups' initial states ``(h, c)``, each ``(K, 2 S_i, L)`` (``S_i`` forward rows, then
    ``S_i`` backward rows), as one batch ``(K, 2 sum S_i, L)``: every group's forward rows, then
    every group's backward rows, groups in order (the layout ``run_chains`` takes)."""
    def rows(t: np.ndarray, backward: bool) -> np.ndarray:
        half = t.shape[1] // 2
        return t[:, half:] if backward else t[:, :half]

    return tuple(np.concatenate([rows(st[i], back) for back in (False, True) for st in states], axis=1)
                 for i in range(2))


def seeded_chain_states(model, seeds: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """Random initial states of ``len(seeds)`` completions as one batch: completion ``i``'s are the
    ones a one-sample ``complete(..., random_state=True, seed=seeds[i])`` draws, so a batched
    roll-out of them gives what the one-sample calls give (to float32 rounding)."""
    return join_chain_states([chain_states(model, 1, True, int(s)) for s in seeds])


def warm_chain_states(model, state, before=None, after=None):
    """The chains' initial ``state`` (``(h, c)``, each ``(K, 2P, L)``: P forward rows, then P backward
    rows) after teacher-forced steps through the frames given around their keys, as ``predict`` warms
    up on its given frames: the forward rows through ``before`` ``(P, U_a, V, C)`` (the frames just
    before key a, in time order), the backward rows through ``after`` ``(P, U_b, V, C)`` (the frames
    just after key b) from the last one back. Either may be None or hold no frames."""
    pairs = state[0].shape[1] // 2
    sides = []
    for rows, frames, n_forward in ((slice(0, pairs), before, pairs), (slice(pairs, None), after, 0)):
        st = (state[0][:, rows], state[1][:, rows])
        if frames is not None and np.shape(frames)[1]:
            x = _frames(frames)
            order = range(x.shape[1]) if n_forward else range(x.shape[1] - 1, -1, -1)
            for i in order:
                st, _ = model.engine.step(st, x[:, i], n_forward=n_forward)
        sides.append(st)
    return tuple(np.concatenate([sides[0][k], sides[1][k]], 1) for k in range(2))


def context_fit(model, before, key_a, after, key_b) -> np.ndarray:
    """``(P,)``: how the model predicts the frames given around P pairs of keys, against the
    trivial predictions (< 1: better than both). On each side with at least two frames
    (``before`` ``(P, U_a, V, C)`` then ``key_a`` ``(P, V, C)``; ``after`` ``(P, U_b, V, C)`` back
    to ``key_b``): a free roll-out from the far frame to the key, as the chains roll, and its mean
    RMS feature error from the second step on over the smaller of standing still's (the far frame)
    and constant velocity's (the far frame's step repeated) on the same frames (``_side_fit``).
    The larger of the two sides; ``inf`` where no side has two frames (nothing shows that the model
    knows this motion)."""
    fits = []
    for frames, key, n_forward in ((before, key_a, None), (after, key_b, 0)):
        if frames is None or np.shape(frames)[1] < 2:
            continue
        key = np.asarray(key)[:, None]
        if n_forward is None:  # (P, U + 1, V, C) from the far frame to the key
            path = np.concatenate([np.asarray(frames), key], 1)
        else:
            path = np.concatenate([key, np.asarray(frames)], 1)[:, ::-1]
        p = path.shape[0]
        state = model.engine.initial_state(p, 0) if n_forward is None else model.engine.initial_state(0, p)
        rolled, _ = model.engine.rollout(_frames(path[:, 0]), path.shape[1] - 1, state, n_forward=n_forward)
        fits.append(_side_fit(path.astype(np.float64), rolled))
    if not fits:
        return np.full(np.shape(key_a)[0], np.inf)
    return np.max(fits, axis=0)


def _side_fit(path: np.ndarray, rolled: np.ndarray) -> np.ndarray:
    """``(P,)`` for true frames ``path`` ``(P, n, V, C)`` (n >= 3) and a roll-out from ``path[:, 0]``
    ``rolled`` (the same shape, ``rolled[:, 0] = path[:, 0]``): its mean RMS error over frames
    ``2..n-1`` over the smaller of standing still's and constant velocity's."""
    def err(pred):  # (P, n - 2) RMS per frame
        return np.sqrt(np.square(pred - path[:, 2:]).mean((2, 3)))

    steps = np.arange(1, path.shape[1] - 1)[None, :, None, None]
    still = err(path[:, :1]).mean(1)
    constant = err(path[:, 1:2] + (path[:, 1:2] - path[:, :1]) * steps).mean(1)
    return err(rolled[:, 2:]).mean(1) / np.maximum(np.minimum(still, constant), 1e-12)


#: the slowest pace of the frames around the keys (``novelty.training_pace``; ``pace_factor`` for a run
#: stored without the training frames' latent steps) at which the chains are trusted
PACE_TRUST = 0.6
#: frames on each side of the keys that ``meshseq complete`` gives the chains (``--context``)
CONTEXT = 7


def context_pace(model, path: np.ndarray) -> np.ndarray:
    """``(P,)`` ``pace_factor`` of frames ``path`` ``(P, n, V, C)`` (n >= 2, in time order) fed to
    the model's forward chains from their trained state, as ``predict --pace warm-up`` measures its
    given frames: 1 at the model's pace, less where the frames move slower than it expects."""
    x = _frames(path)
    _, expected = _warm_up(model.engine, model.engine.initial_state(x.shape[0], 0), x)
    return pace_factor(_rms(x[:, 1:] - x[:, :-1]), expected)


def context_trust(model, before, key_a, after, key_b, pace_trust: float = PACE_TRUST) -> np.ndarray:
    """``(P,)`` bool: whether the chains between P pairs of keys may keep their own motion (the
    corrected join): both keys familiar (``meshseq.novelty``: the guard's weight is 1) and the frames
    given around them (``before`` ``(P, U_a, V, C)`` up to ``key_a``, ``key_b`` then ``after``
    ``(P, U_b, V, C)``) familiar motion (``side_trust`` on each side with frames; False where neither
    side has any). A model stored without the training frames' latents: ``context_fit`` < 1 instead."""
    if getattr(model, "novelty", None) is None:
        return context_fit(model, before, key_a, after, key_b) < 1.0
    a, b = _frames(key_a), _frames(key_b)
    # both keys' poses, each alone (a pair of keys is not a step), in one batch
    weights = novelty_weights(model, np.concatenate([a, b])[:, None])
    trusted = np.minimum(weights[:len(a)], weights[len(a):]) >= 1.0
    sides = []
    if before is not None and np.shape(before)[1]:
        sides.append(np.concatenate([_frames(before), a[:, None]], 1))
    if after is not None and np.shape(after)[1]:
        sides.append(np.concatenate([b[:, None], _frames(after)], 1))
    if not sides:
        return np.zeros(len(a), bool)
    for path in sides:
        trusted &= side_trust(model, path, pace_trust)
    return trusted


def side_trust(model, path: np.ndarray, pace_trust: float = PACE_TRUST) -> np.ndarray:
    """``(P,)`` bool: frames ``path`` ``(P, n, V, C)`` (n >= 2, in time order) beside a key move at
    the pace training shows at their poses (``novelty.training_pace`` >= ``pace_trust``) and their
    last step heads where training went from there (prediction's direction check: its
    ``novelty.direction_weight`` is 1). A model stored without the training frames' latent steps:
    ``context_pace`` >= ``pace_trust``."""
    x = _frames(path)
    reference = model.novelty
    if reference.steps is None:
        return context_pace(model, x) >= pace_trust
    z = model.encode(x)
    return (novelty.training_pace(z, reference) >= pace_trust) & (novelty.heading_weight(z, reference) >= 1.0)


def run_context_chains(model, keys_a, keys_b, n_between: int, state, before=None, after=None,
                       trust: bool = True):
    """``run_chains`` from ``state`` warmed up on the frames around the keys (``warm_chain_states``;
    ``before`` / ``after`` ``(P, U, V, C)`` or None), and ``trusted`` ``(P,)``: whether the chains
    may keep their own motion (``context_trust``); None where no frames are given or not ``trust``.
    Returns ``(forward, backward, trusted)``."""
    trusted = None
    if before is not None or after is not None:
        state = warm_chain_states(model, state, before, after)
        if trust:
            trusted = context_trust(model, before, keys_a, after, keys_b)
    forward, backward = run_chains(model, keys_a, keys_b, n_between, state)
    return forward, backward, trusted


def run_chains(model, keys_a, keys_b, n_between: int, state) -> tuple[np.ndarray, np.ndarray]:
    """The forward chains from ``keys_a`` and the backward chains from ``keys_b`` as ONE roll-out
    (the weights read once a step for all of them).

    Args:
        keys_a, keys_b: ``(P, V, 9)`` scaled features, one pair of keys per completion.
        state: ``(h, c)``, each ``(K, 2P, L)``: P forward rows, then P backward rows.
    Returns:
        ``(forward, backward)``, each ``(P, n_between + 2, V, 9)``; ``forward[p, 0]`` is
        ``keys_a[p]``, ``backward[p, 0]`` is ``keys_b[p]`` (the backward chain's own order).
    """
    a, b = _frames(keys_a), _frames(keys_b)
    pairs = a.shape[0]
    frames, _ = model.engine.rollout(np.concatenate([a, b]), n_between + 1, state, n_forward=pairs)
    return frames[:pairs], frames[pairs:]


def join_chains(forward: np.ndarray, backward: np.ndarray, join: str, blend: int = 2,
                trusted: np.ndarray | None = None, line: np.ndarray | None = None):
    """``(frames (P, n, V, C), meeting frames (P,), gaps (P,))`` of P chain pairs ``(P, n, V, C)``
    (``run_chains``) joined by ``join``, all pairs at once: what ``corrected_crossfade`` or
    ``stitch_chains`` give pair by pair, and for ``anchored`` the corrected frames drawn toward
    ``line`` ``(P, n, V, C)`` (``anchor_line``; default the keys' straight line) by ``reach_weights``,
    except the pairs ``trusted`` ``(P,)`` bool marks (``context_trust``), which keep the corrected join;
    ``meeting``/``gap``: where the raw chains agree best (``stitch_chains``' choice), whatever the join."""
    pairs, n = forward.shape[:2]
    back = backward[:, ::-1]  # forward time order: back[:, -1] = key b
    diff = forward - back
    dist = np.sqrt(np.einsum("pnvc,pnvc->pn", diff, diff) / np.prod(forward.shape[2:]))  # (P, n) RMS
    inner = np.arange(1, n - 1) if n > 2 else np.arange(n)
    meets = inner[np.argmin(dist[:, inner], axis=1)]
    gaps = dist[np.arange(pairs), meets]
    if join == "stitch":
        frames = np.stack([stitch_chains(f, b, blend)[0] for f, b in zip(forward, backward)])
        return frames, meets, gaps.astype(np.float64)
    # corrected_crossfade in one expression: (1 - r) F + r B - r (1 - r) D, with D the sum of both
    # chains' misses of their far keys (F[-1] - key b) + (B[0] - key a)
    ramp = np.linspace(0.0, 1.0, n).astype(forward.dtype)[None, :, None, None]
    miss = (forward[:, -1] - backward[:, 0]) + (backward[:, -1] - forward[:, 0])  # (P, V, C)
    frames = forward * (1 - ramp)
    frames += np.multiply(back, ramp, out=diff)  # (diff's memory reused: same bits, no temporaries)
    frames -= np.multiply(ramp * (1 - ramp), miss[:, None], out=diff)
    if join == "anchored":
        if line is None:
            line = keys_line(forward[:, 0], backward[:, 0], n)
        w = (1 - line_shares(forward, backward, trusted)).astype(forward.dtype)[:, None, None, None]
        frames = line + w * (frames - line)
    return frames, meets, gaps.astype(np.float64)


#: The line between two keys that the ``anchored`` join draws its chains toward (``anchor_line``).
LINES = ("geodesic", "straight")


def anchor_line(model, keys_a: np.ndarray, keys_b: np.ndarray, n: int, line: str = "geodesic") -> np.ndarray:
    """Scaled features ``(P, n, V, C)`` from ``keys_a`` to ``keys_b`` ``(P, V, C)`` (scaled), keys
    included: ``straight``, every channel linear; ``geodesic`` (default), the same but each vertex's
    rotation turned along its shortest path (``acap.interpolation.geodesic_interpolation``, on the
    unscaled features). Where a rotation turns far between the keys or its log lies on an outer
    branch, the straight line passes through poses neither key is near (method.md, "5. Synthesis")."""
    if line not in LINES:
        raise MeshseqError(f"unknown line {line!r}; expected one of {', '.join(LINES)}")
    a, b = np.asarray(keys_a), np.asarray(keys_b)
    if line == "straight":
        return keys_line(a, b, n)
    from meshseq.acap.interpolation import geodesic_interpolation

    raw = model.scaling.invert(np.stack([a, b]).astype(np.float64))  # (2, P, V, C)
    frames = model.scaling.apply(geodesic_interpolation(raw[0], raw[1], n - 2))  # (n, P, V, C)
    return np.ascontiguousarray(frames.swapaxes(0, 1), dtype=a.dtype)


def keys_line(keys_a: np.ndarray, keys_b: np.ndarray, n: int) -> np.ndarray:
    """``(P, n, ...)`` straight lines from ``keys_a`` to ``keys_b`` ``(P, ...)``, keys included, in
    their dtype."""
    ramp = np.linspace(0.0, 1.0, n).astype(keys_a.dtype).reshape((1, n) + (1,) * (keys_a.ndim - 1))
    return keys_a[:, None] * (1 - ramp) + keys_b[:, None] * ramp


def line_shares(forward: np.ndarray, backward: np.ndarray, trusted: np.ndarray | None = None) -> np.ndarray:
    """``(P,)`` share of the line between the keys in the ``anchored`` join of P chain pairs
    ``(P, n, V, C)``: ``1 - reach_weights``, 0 for the pairs ``trusted`` ``(P,)`` marks."""
    w = reach_weights(forward, backward)
    return 1.0 - (w if trusted is None else np.where(trusted, 1.0, w))


def reach_weights(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """``(P,)`` weight in [0, 1] of the chains' motion against the straight line between the keys,
    for P chain pairs ``(P, n, V, C)`` (``run_chains``): ``1 - m / d``, with ``m`` the mean of the
    two chains' squared misses of their far keys and ``d`` the squared distance between the keys.

    A chain that lands near the far key knows this gap's motion; one that misses it by as much as
    the keys are apart (a pose held still between two keys, while the chains play the motion they
    learned) does not, and the join falls back to interpolation, which is then right. Body set
    (1,000 vertices, 600 iterations; mean in-between error x 1e-4 at gaps 5 / 10 / 20): on the
    validation blocks corrected 148 / 273 / 495, anchored 160 / 295 / 514, linear 161 / 300 / 539;
    on the same bodies with holds and slow-downs (``make-bodies --tempo varied``) corrected
    114 / 183 / 412, anchored 79 / 152 / 362, linear 79 / 153 / 363.
    """
    miss = 0.5 * (np.square(forward[:, -1] - backward[:, 0]).sum((1, 2))
                  + np.square(backward[:, -1] - forward[:, 0]).sum((1, 2)))
    keys = np.square(backward[:, 0] - forward[:, 0]).sum((1, 2))
    return np.clip(1.0 - miss / np.maximum(keys, 1e-12), 0.0, 1.0)


def stitch_chains(forward: np.ndarray, backward: np.ndarray, blend: int = 2) -> tuple[np.ndarray, int, float]:
    """Join a forward chain and a backward chain that span the same frames.

    Args:
        forward: ``(n, V, C)``: ``forward[0]`` is key a, then the forward chain's predictions.
        backward: ``(n, V, C)`` in the backward chain's own order: ``backward[0]`` is key b.
        blend: half-width of the linear blend around the meeting frame.
    Returns:
        ``(frames (n, V, C), meeting index, RMS gap there)``; ``frames[0]`` = forward[0] and
        ``frames[-1]`` = backward[0] exactly.
    """
    n = len(forward)
    back = backward[::-1]  # in forward time order: back[-1] = key b
    dist = np.sqrt(((forward - back) ** 2).mean(axis=(1, 2)))
    inner = np.arange(1, n - 1) if n > 2 else np.arange(n)
    meet = int(inner[np.argmin(dist[inner])])
    i = np.arange(n)
    alpha = np.clip((i - meet + blend + 0.5) / (2 * blend + 1), 0.0, 1.0)
    alpha[0], alpha[-1] = 0.0, 1.0
    out = (1 - alpha)[:, None, None] * forward + alpha[:, None, None] * back
    return out, meet, float(dist[meet])


def corrected_crossfade(forward: np.ndarray, backward: np.ndarray) -> np.ndarray:
    """Join two chains spanning the same frames: each chain minus its miss of the far key, spread
    linearly over the gap (so it ends exactly on that key), then a linear crossfade of the two.

    ``forward (n, V, C)``: ``forward[0]`` is key a; ``backward (n, V, C)`` in its own order,
    ``backward[0]`` is key b. Returns ``(n, V, C)`` with ``[0]`` = key a and ``[-1]`` = key b.

    Why (measured on the recipe study's validation blocks, never on evaluation frames,
    ``benchmarks/rollout_study.py``; docs/results.md "Completion"): the chains slow down and drift
    after a few steps, and the paper's stitch keeps that drift up to the meeting frame, then
    closes the remaining distance in a 5-frame blend; on the body set at gap 10 the stitch was
    1.13x linear interpolation and this join 0.92x.
    """
    fwd_c, back_c = corrected_chains(forward, backward)
    ramp = np.linspace(0.0, 1.0, len(forward))[:, None, None]
    return (1.0 - ramp) * fwd_c + ramp * back_c


def corrected_chains(forward: np.ndarray, backward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both chains ``(n, V, C)`` in forward time order, each minus its miss of the far key spread
    linearly over the gap: ``[0]`` of the backward one is key a, ``[-1]`` of the forward one key b."""
    ramp = np.linspace(0.0, 1.0, len(forward))[:, None, None]
    back = backward[::-1]  # forward time order: back[-1] = key b
    fwd_c = forward - ramp * (forward[-1] - backward[0])
    back_c = back - (1.0 - ramp) * (back[0] - forward[0])
    return fwd_c, back_c


#: How ``complete`` joins its two chains: ``anchored`` (default), ``corrected`` or ``stitch`` (the paper's).
JOINS = ("anchored", "corrected", "stitch")
#: The completion methods made of the two chains (``baselines.COMPLETION_METHODS``) and their join.
METHOD_JOINS = {"ours": "anchored", "corrected": "corrected", "stitch": "stitch"}


def sample_join(method: str, random_state: bool) -> str:
    """The join of completion ``method`` (``METHOD_JOINS``): samples of ``ours`` drawn from random
    initial states keep their own motion (``corrected``; the ``anchored`` pull would fold the
    samples that miss the far key onto one straight line, leaving no choice)."""
    join = METHOD_JOINS[method]
    return "corrected" if join == "anchored" and random_state else join


def complete(model, key_a, key_b, n_between: int, samples: int = 1, random_state: bool | None = None,
             seed: int | None = None, blend: int = 2, join: str | None = None,
             seeds: list[int] | None = None, before=None, after=None, line: str = "geodesic") -> Completion:
    """Fill ``n_between`` frames between two keys with the two chains, joined by ``join``.

    All samples' chains run as one batched roll-out (``run_chains``).

    Args:
        key_a, key_b: ``(V, 9)`` scaled features of the keys.
        n_between: frames strictly between the keys (>= 0).
        samples: how many completions (each from its own random initial states).
        random_state: draw initial states from U(-0.1, 0.1) (default: when ``samples > 1``);
            otherwise the trained states +0.1 (forward) and -0.1 (backward).
        seed: seed of those random states (one generator for all samples).
        seeds: instead of ``samples`` and ``seed``: one seed per sample, sample ``i`` drawing the
            random states a one-sample call with ``seed=seeds[i]`` draws (``seeded_chain_states``).
        join: ``anchored`` (``corrected`` drawn toward the keys' straight line: ``reach_weights``),
            ``corrected`` (``corrected_crossfade``) or ``stitch`` (``stitch_chains`` with ``blend``);
            default ``anchored``, ``corrected`` for random-state samples (``sample_join``).
            ``stitch`` / ``gap`` of the result are the raw chains' meeting frame and distance
            either way.
        before, after: ``(U_a, V, 9)`` / ``(U_b, V, 9)`` scaled features of the frames given just
            before key a / just after key b (time order; ``CONTEXT`` frames by default in the
            command). The chains warm up on them (``warm_chain_states``), and where the keys are
            familiar and those frames move as training does there (``context_trust``) the
            ``anchored`` join keeps the chains' own motion (the corrected join) instead of
            drawing it toward the line.
        line: the line between the keys that ``anchored`` draws toward (``anchor_line``).
    """
    random_state = (samples > 1 if random_state is None else random_state) or seeds is not None
    if join is None:
        join = sample_join("ours", random_state)
    if join not in JOINS:
        raise MeshseqError(f"unknown join {join!r}; expected one of {', '.join(JOINS)}")
    if n_between < 0:
        raise MeshseqError(f"frames between keys must be >= 0, got {n_between}")
    if seeds is not None:
        samples, state = len(seeds), seeded_chain_states(model, seeds)
    else:
        state = chain_states(model, samples, random_state, seed)
    keys_a, keys_b = (np.broadcast_to(_frames(k)[None], (samples,) + np.shape(k)) for k in (key_a, key_b))
    ctx_a, ctx_b = (None if c is None else np.broadcast_to(_frames(c), (samples,) + np.shape(c))
                    for c in (before, after))
    forward, backward, _ = run_context_chains(model, keys_a, keys_b, n_between, state, ctx_a, ctx_b, trust=False)
    trusted = None
    if join == "anchored" and (before is not None or after is not None):  # one pair of keys: trusted once
        one = [None if c is None else c[:1] for c in (ctx_a, ctx_b)]
        trusted = np.repeat(context_trust(model, one[0], keys_a[:1], one[1], keys_b[:1]), samples)
    anchored = join == "anchored"
    anchor = anchor_line(model, keys_a, keys_b, n_between + 2, line) if anchored else None
    frames, meets, gaps = join_chains(forward, backward, join, blend, trusted=trusted, line=anchor)
    frames[:, 0] = np.asarray(key_a)
    frames[:, -1] = np.asarray(key_b)
    return Completion(frames, meets, gaps, line_share=line_shares(forward, backward, trusted) if anchored else None)


def complete_cma(model, key_a, key_b, n_between: int, max_evals: int = 400, max_seconds: float = 60.0,
                 sigma: float = 0.05, popsize: int | None = None, seed: int = 0) -> Completion:
    """The optimisation baseline: CMA-ES over the forward chain's initial state ``(h, c)``.

    The objective is the mean squared difference between the chain's last frame and key b; the
    whole population is rolled out as one batch. Stops after ``max_evals`` evaluations or
    ``max_seconds``, whichever first. The last frame is then set to key b.
    """
    import cma

    a, b = _frames(key_a), _frames(key_b)
    n = n_between + 2
    h0, c0 = model.engine.initial_state(1, 0)
    shape = h0.shape  # (K, 1, L)
    x0 = np.concatenate([h0.reshape(-1), c0.reshape(-1)]).astype(np.float64)
    opts = {"seed": int(seed) + 1, "maxfevals": int(max_evals), "verbose": -9, "CMA_diagonal": True}
    if popsize:
        opts["popsize"] = int(popsize)
    es = cma.CMAEvolutionStrategy(x0, sigma, opts)
    half = x0.size // 2

    def rollout(states: np.ndarray) -> np.ndarray:
        p = len(states)
        st = np.asarray(states, dtype=np.float32)
        h = np.ascontiguousarray(st[:, :half].reshape(p, shape[0], shape[2]).transpose(1, 0, 2))
        c = np.ascontiguousarray(st[:, half:].reshape(p, shape[0], shape[2]).transpose(1, 0, 2))
        return model.engine.rollout(np.broadcast_to(a[None], (p,) + a.shape), n - 1, (h, c), n_forward=p)[0]

    start = time.monotonic()
    while not es.stop() and time.monotonic() - start < max_seconds:
        pop = es.ask()
        last = rollout(np.asarray(pop))[:, -1]
        loss = ((last - b[None]) ** 2).mean(axis=(1, 2))
        es.tell(pop, loss.astype(np.float64).tolist())
    best = es.result.xbest if es.result.xbest is not None else x0
    frames = rollout(np.asarray(best)[None])
    gap = float(np.sqrt(((frames[0, -1] - np.asarray(key_b)) ** 2).mean()))
    frames[:, 0] = np.asarray(key_a)
    frames[:, -1] = np.asarray(key_b)
    return Completion(frames, np.array([n - 1]), np.array([gap]), evaluations=int(es.countevals))


def complete_keyframes(model, key_vertices: np.ndarray, gaps: list[int], method: str = "ours",
                       samples: int = 1, seed: int = 0, cma_evals: int = 400,
                       cma_seconds: float = 60.0, before: np.ndarray | None = None,
                       after: np.ndarray | None = None, line: str = "geodesic",
                       vertex_share: float | None = None) -> np.ndarray:
    """Fill every gap between consecutive keyframes and return vertices through all of them.

    Args:
        key_vertices: ``(K, V, 3)`` keyframes; gaps: ``K - 1`` numbers of frames to generate
            between consecutive keys.
        method: ``ours`` (the chains, corrected and crossfaded), ``stitch`` (the chains stitched as
            in the paper), ``cma`` (CMA-ES baseline), ``linear`` (ACAP interpolation) or
            ``linear_vertices`` (straight lines between the keys' vertices).
        samples: completions from random initial states (``ours`` only; 1 = the trained states).
        before, after: ``(U_a, V, 3)`` / ``(U_b, V, 3)`` frames given just before the first key and
            just after the last (time order): with ``ours`` and one sample, the first gap's forward
            chain and the last gap's backward chain warm up on them (``complete``'s ``before`` /
            ``after``); the other methods use the keys alone (``stitch`` is the paper's), and so do
            several samples (warming their random initial states up on the same frames would pull
            them together: on crane the diversity of 8 fell by 13%).
        line: what ``ours``' anchored join draws toward (``anchor_line``).
        vertex_share: how far the part of ``ours`` taken from that line moves on toward the straight
            lines between the keys' vertices (``blend_toward_vertices``); default the model's
            (``meshseq.inbetween``: fitted on its training frames, 0 for runs trained before).
    Returns:
        ``(samples, K + sum(gaps), V, 3)`` vertices, exactly the keys at the key frames.
    """
    from meshseq.baselines import COMPLETION_METHODS, linear_interpolation

    if method not in COMPLETION_METHODS:
        raise MeshseqError(f"unknown completion method {method!r}; expected one of {COMPLETION_METHODS}")
    if samples > 1 and method not in METHOD_JOINS:
        raise MeshseqError(f"{samples} samples need the method 'ours' or 'stitch'")
    keys = np.asarray(key_vertices, dtype=np.float64)
    if method == "linear_vertices":
        parts = [linear_interpolation(keys[i], keys[i + 1], gap)[int(i > 0):] for i, gap in enumerate(gaps)]
        return np.concatenate(parts)[None]
    warm = method == "ours" and samples == 1
    key_f, ctx_a, ctx_b = keyframe_features(model, keys, before if warm else None, after if warm else None)
    parts, anchors, offset, shares = [], {0: keys[0]}, 0, []
    for i, gap in enumerate(gaps):  # per gap; all samples of a gap run as one batched roll-out
        if method in METHOD_JOINS:
            seeds = [seed * 1000 + s * 97 + i for s in range(samples)] if samples > 1 else None
            done = complete(model, key_f[i], key_f[i + 1], gap, seeds=seeds, join=sample_join(method, samples > 1),
                            before=ctx_a if i == 0 else None, after=ctx_b if i == len(gaps) - 1 else None,
                            line=line)
            f = done.frames
            if done.line_share is not None:
                shares.append((offset, gap, done.line_share))
        elif method == "cma":
            f = complete_cma(model, key_f[i], key_f[i + 1], gap, max_evals=cma_evals,
                             max_seconds=cma_seconds, seed=seed + i).frames
        else:
            f = linear_interpolation(key_f[i], key_f[i + 1], gap)[None]
        parts.append(f if i == 0 else f[:, 1:])  # (samples, frames, V, 9)
        offset += gap + 1
        anchors[offset] = keys[i + 1]
    out = assemble_vertices(model, np.concatenate(parts, axis=1), anchors)
    share = model.vertex_share if vertex_share is None else vertex_share
    for start, gap, line_share in shares if share else ():
        out[:, start:start + gap + 2] = blend_toward_vertices(out[:, start:start + gap + 2], share * line_share)
    return out


def blend_toward_vertices(frames: np.ndarray, share: np.ndarray) -> np.ndarray:
    """Completed vertices ``(P, n, V, 3)`` (keys first and last) moved toward the straight lines
    between their keys by ``share`` ``(P,)`` (0: unchanged, 1: the lines); the keys stay."""
    s = np.asarray(share, dtype=np.float64)
    if not np.any(s):
        return frames
    return frames + s[:, None, None, None] * (keys_line(frames[:, 0], frames[:, -1], frames.shape[1]) - frames)


def keyframe_features(model, keys: np.ndarray, before=None, after=None):
    """Scaled features of keyframes ``(K, V, 3)`` and of the frames given before and after them,
    ``(K, V, 9)`` and ``(U_a, V, 9)`` / ``(U_b, V, 9)`` (None where none are given). Extracted in
    one pass in time order, so that the context's rotations follow on from the keys'; without
    context, the keys' features alone (as before context was used)."""
    n_a = 0 if before is None else len(before)
    n_b = 0 if after is None else len(after)
    if not n_a and not n_b:
        return model.features(keys), None, None
    parts = [np.asarray(p, dtype=np.float64) for p in (before, keys, after) if p is not None and len(p)]
    f = model.features(np.concatenate(parts))
    k = len(keys)
    return f[n_a:n_a + k], (f[:n_a] if n_a else None), (f[n_a + k:] if n_b else None)


# --------------------------------------------------------------------------------------------
# vertices


def assemble_vertices(model, features: np.ndarray, anchors: dict[int, np.ndarray], decay: int = 8) -> np.ndarray:
    """Vertices ``(T, V, 3)`` from scaled features ``(T, V, 9)`` that pass exactly through anchors;
    or, for S samples ``(S, T, V, 9)`` (one reconstruction of all ``S T`` frames), ``(S, T, V, 3)``.

    ``anchors`` maps frame index -> true vertices ``(V, 3)`` (given frames or keyframes); anchor
    frames are output as given. Every other frame is the reconstruction of its features (centred)
    plus a correction interpolated from the anchors around it (``anchor_weights``): each anchor
    contributes its centroid and its reconstruction residual (true minus reconstructed vertices),
    linearly between two anchors and fading over ``decay`` frames after the last one (a
    prediction), so the motion continues from the last given frame without a jump.
    """
    f = np.asarray(features)
    batched = f.ndim == 4
    f = f if batched else f[None]
    recon = model.vertices(f.reshape(-1, *f.shape[2:])).reshape(f.shape[:3] + (3,))  # (S, T, V, 3) centred
    out = pass_through_anchors(recon, anchors, decay)
    return out if batched else out[0]


def anchor_weights(n_frames: int, keys: list[int], decay: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """``(w_corr, w_centroid)``, each ``(T, A)``: frame ``t`` gets ``sum_k w_corr[t, k] corr_k +
    w_centroid[t, k] centroid_k`` added (``corr_k`` = anchor k's vertices minus their reconstruction;
    ``keys`` sorted anchor frames). Between two anchors ``ka < t < kb``: ``corr`` linearly,
    ``(1 - s, s)`` with ``s = (t - ka) / (kb - ka)``; outside them, nearest anchor k:
    ``centroid_k + fade (corr_k - centroid_k)``, ``fade = max(0, 1 - |t - k| / decay)``."""
    t = np.arange(n_frames)[:, None]
    k = np.asarray(keys)[None, :]
    w_corr = np.zeros((n_frames, len(keys)))
    w_cent = np.zeros((n_frames, len(keys)))
    after = np.searchsorted(keys, t[:, 0], side="right")  # index of the first anchor > t
    inside = (after > 0) & (after < len(keys))
    rows = np.flatnonzero(inside)
    ka, kb = k[0, after[rows] - 1], k[0, after[rows]]
    s = (rows - ka) / (kb - ka)
    w_corr[rows, after[rows] - 1] = 1 - s
    w_corr[rows, after[rows]] += s  # (t == ka: s = 0, the anchor itself)
    rows = np.flatnonzero(~inside)
    near = np.where(after[rows] == 0, 0, len(keys) - 1)
    dist = np.abs(rows - k[0, near])
    fade = np.maximum(0.0, 1.0 - dist / decay) if decay > 0 else np.zeros(len(rows))
    w_corr[rows, near] = fade
    w_cent[rows, near] = 1.0 - fade
    return w_corr, w_cent


def pass_through_anchors(recon: np.ndarray, anchors: dict[int, np.ndarray], decay: int = 8) -> np.ndarray:
    """Reconstructions ``(S, T, V, 3)`` corrected to pass through ``anchors`` (``assemble_vertices``)."""
    keys = sorted(anchors)
    if not keys:
        return recon
    true = np.stack([np.asarray(anchors[k], dtype=np.float64) for k in keys])  # (A, V, 3)
    corr = true[None] - recon[:, keys]  # (S, A, V, 3): centroid + residual
    w_corr, w_cent = anchor_weights(recon.shape[1], keys, decay)
    # (T, A) @ (S, A, V*3): one matmul (the einsum took 0.18 s for 8 crane completions)
    out = np.matmul(w_corr, corr.reshape(corr.shape[0], len(keys), -1)).reshape(recon.shape)
    out += recon
    out += (w_cent @ true.mean(axis=1))[None, :, None]
    out[:, keys] = true[None]
    return out
