"""Differentiable reconstruction in torch: features ``(B, V, 9)`` -> vertices ``(B, V, 3)``.

The same linear map as ``Reconstructor`` (method.md 2.2-2.3): right-hand side by the sparse
operator ``B``, then the pinned Laplacian's Cholesky factor (cholespy, CPU or CUDA). The solve is
wrapped in an autograd function (the matrix is symmetric, so the backward pass is one more solve
with the same factor), so losses on vertices can be backpropagated to the features.
"""

from __future__ import annotations

import numpy as np
import torch

from meshseq.acap.features import features_to_gradients
from meshseq.acap.parts import PLACEMENT_CHANNELS, body_part, relative_centroids
from meshseq.acap.reconstruct import Reconstructor

#: cholespy's CUDA solver takes at most this many right-hand sides at once.
_CUDA_MAX_RHS = 128


class _CholeskySolve(torch.autograd.Function):
    @staticmethod
    def forward(ctx, solver, max_rhs, b):
        ctx.solver, ctx.max_rhs = solver, max_rhs
        return _solve_columns(solver, b, max_rhs)

    @staticmethod
    def backward(ctx, grad_x):
        return None, None, _solve_columns(ctx.solver, grad_x, ctx.max_rhs)


def _solve_columns(solver, b: torch.Tensor, max_rhs: int | None) -> torch.Tensor:
    b = b.contiguous()
    x = torch.empty_like(b)
    step = b.shape[1] if max_rhs is None else max_rhs
    for s in range(0, b.shape[1], step):
        part = b[:, s:s + step].contiguous()
        out = torch.empty_like(part)
        solver.solve(part, out)
        x[:, s:s + step] = out
    return x


class TorchReconstructor(torch.nn.Module):
    """Features -> vertices as a torch module (centroid at the origin; components at the
    reference's relative offsets).

    Args:
        reconstructor: the numpy reconstructor of the reference mesh (its matrices are reused).
        device, dtype: where and in which precision to solve (float32 or float64).
    """

    def __init__(self, reconstructor: Reconstructor, device: str | torch.device = "cpu",
                 dtype: torch.dtype = torch.float32):
        super().__init__()
        import cholespy

        device = torch.device(device)
        self.n_vertices = reconstructor.topology.n_vertices
        op = reconstructor.rhs_operator.tocoo()
        index = torch.as_tensor(np.stack([op.row, op.col]), dtype=torch.int64)
        with torch.sparse.check_sparse_tensor_invariants():  # explicitly (see model._csr)
            rhs = torch.sparse_coo_tensor(index, torch.as_tensor(op.data, dtype=dtype), size=op.shape).coalesce()
        self.register_buffer("rhs_operator", rhs.to(device))
        self.register_buffer("free", torch.as_tensor(reconstructor.free, device=device))
        labels = reconstructor.topology.component_labels
        self.register_buffer("labels", torch.as_tensor(labels, device=device))
        self.n_components = reconstructor.topology.n_components
        self.register_buffer("offsets", torch.as_tensor(reconstructor.reference_offsets, dtype=dtype, device=device))
        rel = relative_centroids(reconstructor.reference[None], reconstructor.topology)[0]  # (C, 3), at rest
        self.register_buffer("reference_placement", torch.as_tensor(rel, dtype=dtype, device=device))
        self.placement = reconstructor.placement  # what 12-channel features' placement channels measure from
        if self.n_components > 1:  # ``anchor`` placement (acap.parts.anchored_shifts)
            self.register_buffer("anchors", torch.as_tensor(reconstructor.anchors, device=device))
            self.register_buffer("anchor_gaps", torch.as_tensor(reconstructor.anchor_gaps, dtype=dtype, device=device))
            self.body = body_part(reconstructor.topology)
        counts = np.bincount(labels, minlength=self.n_components)
        self.register_buffer("counts", torch.as_tensor(counts, dtype=dtype, device=device))
        reduced = reconstructor._factor.matrix.tocoo()
        solver_type = cholespy.CholeskySolverD if dtype == torch.float64 else cholespy.CholeskySolverF
        self._solver = solver_type(
            reduced.shape[0],
            torch.as_tensor(reduced.row, dtype=torch.int32, device=device),
            torch.as_tensor(reduced.col, dtype=torch.int32, device=device),
            torch.as_tensor(reduced.data, dtype=torch.float64 if dtype == torch.float64 else torch.float32,
                            device=device),
            cholespy.MatrixType.COO,
        )
        self._max_rhs = _CUDA_MAX_RHS if device.type == "cuda" else None

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Vertices ``(B, V, 3)`` (centred) from unscaled features ``(B, V, 9)``; features ``(B, V, 12)``
        place the parts by their placement channels (``meshseq.acap.parts``)."""
        bsz, n = features.shape[0], self.n_vertices
        g = features_to_gradients(features)  # (B, V, 3, 3)
        tv = g.permute(1, 3, 0, 2).reshape(3 * n, 3 * bsz)  # [j*3+c, b*3+a]
        rhs = self.rhs_operator @ tv  # (V, 3B)
        x_free = _CholeskySolve.apply(self._solver, self._max_rhs, rhs[self.free])
        x = torch.zeros((n, 3 * bsz), dtype=x_free.dtype, device=x_free.device).index_copy(0, self.free, x_free)
        verts = x.reshape(n, bsz, 3).permute(1, 0, 2)  # (B, V, 3)
        if self.n_components > 1:
            cents = self._part_means(verts)
            if features.shape[-1] > 9 and self.placement == "anchor":  # acap.parts.anchored_shifts
                gap = self.anchor_gaps[None] + self._part_means(features[..., PLACEMENT_CHANNELS].to(verts.dtype))
                shift = verts[:, self.anchors] + gap - cents
                shift = shift.index_fill(1, torch.tensor([self.body], device=verts.device), 0.0)
            else:
                offsets = self.offsets[None] if features.shape[-1] <= 9 else self._offsets(features[..., PLACEMENT_CHANNELS])
                shift = offsets - (cents - cents[:, :1])
            verts = verts + shift[:, self.labels]
        return verts - verts.mean(dim=1, keepdim=True)

    def _part_means(self, values: torch.Tensor) -> torch.Tensor:
        """Mean of ``values (B, V, 3)`` over each part's vertices ``(B, C, 3)``."""
        sums = torch.zeros((values.shape[0], self.n_components, 3), dtype=values.dtype, device=values.device)
        return sums.index_add(1, self.labels, values) / self.counts[None, :, None]

    def _offsets(self, placement: torch.Tensor) -> torch.Tensor:
        """Parts' centroid offsets from component 0 ``(B, C, 3)`` from placement channels ``(B, V, 3)``."""
        rel = self.reference_placement[None] + self._part_means(placement.to(self.reference_placement.dtype))
        return rel - rel[:, :1]
