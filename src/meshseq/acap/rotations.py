"""Rotation logarithms made consistent over the mesh and over time (method.md 1.4-1.5).

A rotation's axis-angle (w, theta) is ambiguous: (-w, 2 pi - theta) and every theta + 2 pi k
give the same matrix. ACAP picks, per vertex, the representative that agrees with its
neighbours (spatial BFS of the reference code) and, for sequences, with the same vertex in the
previous frame (temporal; removes 2 pi jumps in time that a per-shape method cannot).

Why a greedy temporal pass is not enough: all representatives of one rotation lie on one line
(``(theta + 2 pi m) w``, 2 pi apart), so at most one of them is within pi of the previous frame's
log and the greedy nearest choice is the only jump-free continuation while one exists. But near
``|r| = 2 pi k`` (k >= 1) the exponential map squeezes directions across ``r`` by
``2 |sin(|r|/2)| / |r|``: once a vertex's log has turned past pi, a small rotation change near the
identity needs a log step of several radians, and none within pi may exist. The greedy pass then
also commits, at frames where the rotation truly jumps (>= pi/2 in one frame), to whichever branch
is nearest, which can leave the log on an outer shell for later. :func:`temporal` therefore keeps
the greedy result where it has no step above pi and, on the other vertices, picks the branches of
all frames together (dynamic programming) for the fewest spurious jumps, then the smallest steps.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

from meshseq.mesh import Topology, depth_levels, tree_depths

#: Rotation angles at or below this count as "no rotation" (method.md 1.4).
NO_ROTATION = 1e-6
TWO_PI = 2.0 * np.pi

#: ``temporal-mst`` (the default): the branches over time with the fewest spurious jumps (greedy
#: nearest-previous, repaired by dynamic programming where it jumps) from the first frame walked along
#: its smallest rotation differences (:func:`smallest_turn_tree`), unrotated vertices at log 0;
#: ``temporal``: the same over time from the first frame's breadth-first walk (the default before);
#: ``spatial``: BFS per frame; ``greedy``: the earlier temporal pass (each frame nearest the
#: previous, no repair).
CONSISTENCY_MODES = ("temporal-mst", "temporal", "spatial", "greedy")
#: what features are extracted with unless told otherwise
DEFAULT_CONSISTENCY = CONSISTENCY_MODES[0]
#: The trees a spatial pass walks: ``bfs`` (the reference code's breadth-first tree over the ring
#: graph) or ``mst`` (:func:`smallest_turn_tree`).
TREES = ("bfs", "mst")

#: A step of a vertex's log between consecutive frames longer than this is a jump ...
JUMP_STEP = np.pi
#: ... and spurious (a branch change, not motion) when the rotation itself changes by less than this.
JUMP_MOTION = 0.5 * np.pi


def axis_angle(R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-angle of rotations ``(..., 3, 3)``: unit axes ``(..., 3)`` and angles ``(...)`` in [0, pi].

    The angle uses atan2 of the skew and symmetric parts (accurate near 0 and pi). For angles
    beyond pi/2 the axis comes from the symmetric part ``(R + R^T)/2 - cos(theta) I``, which stays
    accurate where ``sin(theta)`` vanishes; its sign follows the skew part. Angles <= 1e-6 get
    angle 0 and the axis (1, 0, 0) (callers treat them as no rotation).
    """
    vee = np.stack(
        [R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], axis=-1
    )  # = 2 sin(theta) w
    two_sin = np.linalg.norm(vee, axis=-1)
    two_cos = np.einsum("...ii->...", R) - 1.0
    theta = np.arctan2(two_sin, two_cos)
    axis = np.divide(vee, two_sin[..., None], out=np.zeros_like(vee), where=two_sin[..., None] > 0)
    wide = theta > 0.5 * np.pi
    if wide.any():
        Rw, c = R[wide], np.cos(theta[wide])
        sym = 0.5 * (Rw + np.swapaxes(Rw, -1, -2)) - c[:, None, None] * np.eye(3)  # (1 - c) w w^T
        k = np.argmax(np.einsum("nii->ni", sym), axis=-1)
        col = sym[np.arange(len(k)), :, k]
        col /= np.linalg.norm(col, axis=-1, keepdims=True)
        sign = np.where(np.einsum("ni,ni->n", col, vee[wide]) < 0, -1.0, 1.0)
        axis[wide] = col * sign[:, None]
    small = theta <= NO_ROTATION
    theta = np.where(small, 0.0, theta)
    axis[small] = (1.0, 0.0, 0.0)
    return axis, theta


#: A part's lowest vertex roots its BFS unless its angle is this far from the part's median angle.
ATYPICAL_ROOT = 0.25 * np.pi


def typical_roots(theta: np.ndarray, topology: Topology) -> np.ndarray:
    """The BFS root of each part ``(C,)`` for one frame's angles ``theta (V,)``: its lowest vertex,
    or, where that vertex's angle is atypical for its part (further than :data:`ATYPICAL_ROOT` from
    the part's median), the vertex nearest the median.

    The BFS makes every log of a part consistent with its root's principal value. A root whose
    rotation is an outlier (an ill-conditioned end vertex of a thin band, turned 2.6 rad where its
    part turns by 0.06) puts its part on the 2 pi shell: near-identity rotations stored as logs of
    norm near 2 pi, where a small change of rotation takes a log step of radians. Parts whose
    lowest vertex is typical (every mesh this rule was checked on) keep today's tree and logs.
    """
    labels = topology.component_labels
    roots = topology.component_roots.copy()
    median = part_medians(theta, labels, len(roots))
    spread = np.abs(theta - median[labels])
    atypical = spread[roots] > ATYPICAL_ROOT
    if atypical.any():
        by_spread = np.lexsort((spread, labels))  # per part, nearest the median first (ties: lowest vertex)
        first = np.searchsorted(labels[by_spread], np.arange(len(roots)))
        roots[atypical] = by_spread[first[atypical]]
    return roots


def part_medians(values: np.ndarray, labels: np.ndarray, n_parts: int) -> np.ndarray:
    """The median of ``values (V,)`` over each part ``(C,)`` (the mean of the two middle ones for an
    even count, as ``np.median``), by one sort rather than a pass per part."""
    order = np.lexsort((values, labels))
    counts = np.bincount(labels, minlength=n_parts)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    v = values[order]
    return 0.5 * (v[start + (counts - 1) // 2] + v[start + counts // 2])


def smallest_turn_tree(axis: np.ndarray, theta: np.ndarray, topology: Topology,
                       roots: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The walk of one frame's rotations ``axis (V, 3)``, ``theta (V,)`` from ``roots (C,)`` along
    the minimum spanning tree of the ring graph weighted by each edge's rotation difference (the
    angle of ``R_i^T R_j``, independent of the logs' branches).

    A vertex whose rotation is an outlier (an ill-conditioned vertex of a thin band, turned by radians
    where its neighbours turn by hundredths) differs from every neighbour by much, so the tree
    reaches it last, as a leaf, and no other vertex takes its branch from it; the breadth-first
    tree may walk through it and put everything beyond it on the 2 pi shell.

    Returns ``(parent (V,), levels)``: parent -1 at the roots; ``levels[d]`` the vertices d edges
    from their root along the tree.
    """
    e = topology.edges
    q = _unit_quaternions(axis, theta)
    turn = _turn_between(q[e[:, 0]], q[e[:, 1]])
    n = topology.n_vertices
    # csgraph drops explicit zeros: an edge between two equal rotations still weighs a little
    graph = sp.csr_matrix((turn + 1e-12, (e[:, 0], e[:, 1])), shape=(n, n))
    tree = csgraph.minimum_spanning_tree(graph)
    tree = tree + tree.T
    parent = np.full(n, -1, dtype=np.int64)
    for root in roots:
        order, pred = csgraph.breadth_first_order(tree, int(root), directed=False)
        parent[order[1:]] = pred[order[1:]]
    return parent, depth_levels(tree_depths(parent))


def spatial_bfs(axis: np.ndarray, theta: np.ndarray, topology: Topology, tree: str = "bfs") -> np.ndarray:
    """Consistent rotation logs by the reference code's greedy BFS (method.md 1.5).

    Applied level by level over the BFS tree (vectorised over frames and the vertices of a level).

    Args:
        axis: ``(T, V, 3)`` unit axes; theta: ``(T, V)`` angles in [0, pi].
        tree: ``bfs`` (the reference code's), or ``mst``: walk along :func:`smallest_turn_tree` of
            the first frame, and give unrotated vertices log 0 (not their parent's 2 pi shell).
    Returns:
        ``(T, V, 3)`` rotation vectors ``Theta w`` with ``Theta = theta + 2 pi k``.
    """
    w = np.ascontiguousarray(axis.transpose(1, 0, 2)).copy()  # (V, T, 3) vertex-major
    th = np.ascontiguousarray(theta.T).copy()  # (V, T)
    k = np.zeros(th.shape, dtype=np.int64)
    if tree not in TREES:
        raise ValueError(f"unknown tree {tree!r}; expected one of {TREES}")
    roots = typical_roots(theta[0], topology)
    if tree == "mst":
        parent, levels = smallest_turn_tree(axis[0], theta[0], topology, roots)
    elif np.array_equal(roots, topology.component_roots):
        parent, levels = topology.bfs[1], topology.bfs_levels
    else:
        _, parent, depth = topology.bfs_trees(roots)
        levels = depth_levels(depth)
    for level in levels[1:]:
        par = parent[level]
        wj, wi, tj, ti, ki = w[level], w[par], th[level], th[par], k[par]
        small = tj <= NO_ROTATION
        flip = (np.einsum("ntc,ntc->nt", wj, wi) < 0) & ~small
        wj = np.where(flip[..., None], -wj, wj)
        tj = np.where(flip, TWO_PI - tj, tj)
        jump = (np.abs(tj - ti) > np.pi) & ~small
        kj = ki + np.where(jump, np.where(ti < np.pi, -1, 1), 0)
        w[level] = np.where(small[..., None], wi, wj)
        th[level] = tj
        k[level] = np.where(small, 0, kj) if tree == "mst" else kj
    big_theta = th + TWO_PI * k
    return (w * big_theta[..., None]).transpose(1, 0, 2)


def greedy_temporal(axis: np.ndarray, theta: np.ndarray, topology: Topology, tree: str = "bfs") -> np.ndarray:
    """Spatial BFS on the first frame, then each frame's representative nearest the previous frame.

    Every representative ``(theta + 2 pi m) w`` of a rotation lies on the line along its axis (the
    flipped axis -w with 2 pi - theta is m = -1), so with the previous log ``c_{t-1} w_{t-1}`` the
    nearest is ``c_t = theta_t + 2 pi round((w_t . w_{t-1} c_{t-1} - theta_t) / 2 pi)``: the
    sequential part is a recurrence on one number per vertex and frame. A frame with no rotation
    keeps the previous axis (its representatives are 0 and the 2 pi k shells along it).

    Args:
        axis: ``(T, V, 3)``; theta: ``(T, V)``; tree: the first frame's walk (``spatial_bfs``).
    Returns:
        ``(T, V, 3)`` rotation vectors.
    """
    first = spatial_bfs(axis[:1], theta[:1], topology, tree)[0]
    w, base = _lines(axis, theta, first)
    cos_turn = np.einsum("tvc,tvc->tv", w[:-1], w[1:])
    c = np.empty(base.shape)
    c[0] = base[0]
    for t in range(1, len(c)):  # sequential in time by definition; vectorised over vertices
        c[t] = base[t] + TWO_PI * np.round((cos_turn[t - 1] * c[t - 1] - base[t]) / TWO_PI)
    return w * c[..., None]


def _lines(axis: np.ndarray, theta: np.ndarray, first: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The line of every frame's representatives: unit axes ``w (T, n, 3)`` and the principal
    signed angle along it ``(T, n)``; frame 0 is ``first (n, 3)`` itself (its norm along its
    direction), and frames with no rotation take the previous frame's axis (their
    representatives are 0 and the 2 pi k shells)."""
    n_frames, n = theta.shape
    small = theta <= NO_ROTATION
    small[0] = False
    norm0 = np.linalg.norm(first, axis=-1)
    w = axis.copy()
    w[0] = np.divide(first, norm0[:, None], out=np.tile([1.0, 0.0, 0.0], (n, 1)), where=norm0[:, None] > 0)
    if small.any():  # identity frames take the previous axis
        fill = np.maximum.accumulate(np.where(small, 0, np.arange(n_frames)[:, None]), axis=0)
        w = np.take_along_axis(w, fill[..., None], axis=0)
    base = np.where(small, 0.0, theta)
    base[0] = norm0
    return w, base


def temporal(axis: np.ndarray, theta: np.ndarray, topology: Topology, tree: str = "bfs") -> np.ndarray:
    """Rotation logs continuous in time: the fewest spurious jumps, then the smallest steps.

    The greedy pass (:func:`greedy_temporal`) is kept on every vertex whose log never steps by more
    than :data:`JUMP_STEP` (there it is the only jump-free choice); the others get
    :func:`fewest_jumps`. The first frame keeps its spatial BFS logs.

    Args:
        axis: ``(T, V, 3)``; theta: ``(T, V)``; tree: the first frame's walk (``spatial_bfs``).
    Returns:
        ``(T, V, 3)`` rotation vectors.
    """
    out = greedy_temporal(axis, theta, topology, tree)
    if len(out) < 2:
        return out
    steps = np.einsum("tvc,tvc->tv", *(np.diff(out, axis=0),) * 2)
    hit = np.flatnonzero((steps > JUMP_STEP**2).any(axis=0))
    if len(hit):
        reach = float(np.sqrt(np.einsum("tvc,tvc->tv", out[:, hit], out[:, hit]).max()))
        out[:, hit] = fewest_jumps(axis[:, hit], theta[:, hit], out[0, hit], reach)
    return out


def _unit_quaternions(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    half = 0.5 * angle
    return np.concatenate([np.cos(half)[..., None], np.sin(half)[..., None] * axis], axis=-1)


def _turn_between(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Angle ``(...)`` of the rotation from unit quaternions ``p`` to ``q`` ``(..., 4)`` (either sign)."""
    return 2.0 * np.arccos(np.clip(np.abs(np.einsum("...c,...c->...", p, q)), 0.0, 1.0))


def relative_angles(logs: np.ndarray) -> np.ndarray:
    """Angle of the rotation between consecutive frames, ``(T - 1, V)`` for logs ``(T, V, 3)``.

    Independent of the branch of the logs (it compares the rotations they stand for).
    """
    norm = np.linalg.norm(logs, axis=-1)
    axis = np.divide(logs, norm[..., None], out=np.zeros_like(logs), where=norm[..., None] > 0)
    q = _unit_quaternions(axis, norm)
    return _turn_between(q[:-1], q[1:])


def fewest_jumps(axis: np.ndarray, theta: np.ndarray, first: np.ndarray, reach: float = 3 * np.pi) -> np.ndarray:
    """Branches of frames 1.. that minimise (spurious jumps, then sum of squared steps), per vertex.

    Exact dynamic programming (Viterbi) over the representatives ``(theta + 2 pi m) w``,
    ``|m| <= M`` with ``2 pi M >= reach`` (pass the greedy path's largest log norm so that the
    search covers it), vectorised over vertices. A step is a spurious jump when it is longer than
    :data:`JUMP_STEP` while the rotation changes by less than :data:`JUMP_MOTION`. Frames with no
    rotation take the previous frame's axis (their representatives are 0 and the 2 pi k shells).

    Args:
        axis: ``(T, n, 3)``; theta: ``(T, n)``; first: ``(n, 3)`` the logs of frame 0 (kept);
        reach: the largest log norm the search must be able to represent.
    Returns:
        ``(T, n, 3)`` rotation vectors.
    """
    n_frames, n = theta.shape
    w, base = _lines(axis, theta, first)
    norm0 = base[0]
    # rotation change per step, from the principal representatives (branch-independent)
    q = _unit_quaternions(w, base)
    free = _turn_between(q[:-1], q[1:]) >= JUMP_MOTION
    cos_turn = np.einsum("tvc,tvc->tv", w[:-1], w[1:])

    m_max = max(1, int(np.ceil(max(reach, float(norm0.max(initial=0.0))) / TWO_PI)))
    shift = TWO_PI * np.arange(-m_max, m_max + 1)
    k = len(shift)
    cand = base[..., None] + shift  # (T, n, K) signed angles along w
    cand_sq = cand * cand
    # every path's sum of squared steps is below this, so one jump outweighs any smoothness gain
    penalty = n_frames * (2.0 * np.abs(cand).max() + 1.0) ** 2 + 1.0
    cost = np.full((n, k), np.inf)
    cost[:, m_max] = 0.0  # frame 0: the given logs (m = 0)
    back = np.empty((n_frames, n, k), dtype=np.int16)
    rows = np.arange(n)
    for t in range(1, n_frames):
        d2 = cand_sq[t - 1][:, :, None] + cand_sq[t][:, None, :] \
            - (2.0 * cos_turn[t - 1])[:, None, None] * cand[t - 1][:, :, None] * cand[t][:, None, :]
        jump = (d2 > JUMP_STEP**2) & ~free[t - 1][:, None, None]
        total = cost[:, :, None] + d2 + penalty * jump  # (n, K from, K to)
        back[t] = np.argmin(total, axis=1)
        cost = np.take_along_axis(total, back[t][:, None, :], axis=1)[:, 0]
    out = np.empty((n_frames, n, 3))
    out[0] = first
    state = np.argmin(cost, axis=1)
    for t in range(n_frames - 1, 0, -1):
        out[t] = w[t] * cand[t, rows, state][:, None]
        state = back[t, rows, state]
    return out


def consistent_logs(axis: np.ndarray, theta: np.ndarray, topology: Topology, mode: str = DEFAULT_CONSISTENCY) -> np.ndarray:
    """Rotation vectors ``(T, V, 3)`` made consistent by ``mode`` (one of CONSISTENCY_MODES)."""
    if mode == "temporal":
        return temporal(axis, theta, topology)
    if mode == "temporal-mst":
        return temporal(axis, theta, topology, tree="mst")
    if mode == "spatial":
        return spatial_bfs(axis, theta, topology)
    if mode == "greedy":
        return greedy_temporal(axis, theta, topology)
    raise ValueError(f"unknown consistency mode {mode!r}; expected one of {CONSISTENCY_MODES}")
