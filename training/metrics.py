"""The accuracy figures of a predicted pad mesh, one definition for every report.

Evaluation (``python -m tactile_deploy.training evaluate``), ``tactile-deploy bench predictor``, the training
run's held-out metrics and the model card all call :func:`mesh_metrics`. Errors are per node:
the Euclidean distance (um) between the predicted and the true displacement (sensor frame), and
each figure is the root mean square of those distances over a set of nodes:

* ``contact_patch_rmse_um``: the sensing nodes in contact with the indenter (the truth's contact
  mask), over all contacts of the set: where grasp forces, contact patches and slip are read;
* ``deepest_node_error_pct``: per contact, the predicted depth (-u_z) of the truth's deepest
  sensing node minus its true depth, in % of the true depth; ``mean`` (signed: < 0 = too shallow),
  ``mean_abs`` and ``p95_abs`` over the contacts;
* ``all_node_rmse_um``: every node (backplate included, as the paper's vertex RMSE, whose
  per-coordinate form is ``all_node_rmse_um / sqrt(3)``);
* ``surface_rmse_um`` (sensing layer) and ``interior_rmse_um`` (the free layers below it).
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from tactile_deploy.fileformat import StrictModel


class DeepestNodeError(StrictModel):
    """The truth's deepest sensing node: predicted depth minus true depth, % of the true depth."""

    mean: float = Field(description="Signed mean over the contacts, % (< 0: too shallow).")
    mean_abs: float = Field(description="Mean of the absolute error over the contacts, %.")
    p95_abs: float = Field(description="95th percentile of the absolute error over the contacts, %.")


class MeshMetrics(StrictModel):
    """The figures of :func:`mesh_metrics` as written into reports and model cards."""

    n_contacts: int = Field(ge=0)
    all_node_rmse_um: float = Field(ge=0, description="RMS per-node Euclidean error over every node, um.")
    surface_rmse_um: float = Field(ge=0, description="The same over the sensing layer, um.")
    interior_rmse_um: float = Field(ge=0, description="The same over the free layers below it, um.")
    relative_error: float = Field(ge=0, description="|pred - true| / |true| over all coordinates.")
    contact_patch_rmse_um: float | None = Field(
        None, ge=0, description="RMS per-node Euclidean error over the sensing nodes in contact, um.")
    contact_nodes: int | None = Field(None, ge=0, description="Sensing nodes in contact, summed over the contacts.")
    deepest_node_error_pct: DeepestNodeError
    lift_ratio: float | None = Field(
        None, ge=0, description="The physics lift's contact-patch RMSE over this method's (> 1: better than the lift).")


def mesh_metrics(pred_mm: np.ndarray, true_mm: np.ndarray, contact_mask: np.ndarray | None, n_plane: int,
                 free_layers: int | None = None) -> dict:
    """Figures (module docstring) of predicted displacements (N, n, 3) mm against the truth (N, n, 3) mm.

    contact_mask : (N, n_plane) bool, the sensing nodes in contact (None: no contact-patch figure).
    n_plane : sensing nodes (the first ``n_plane`` nodes); ``free_layers``: node layers that move
    (default: all but the last, the bonded backplate).
    """
    pred = np.asarray(pred_mm, np.float64)
    true = np.asarray(true_mm, np.float64)
    if pred.shape != true.shape or pred.ndim != 3 or pred.shape[2] != 3:
        raise ValueError(f"pred and true must both be (N, n, 3), got {pred.shape} and {true.shape}")
    n_nodes = pred.shape[1]
    free_layers = free_layers if free_layers is not None else n_nodes // n_plane - 1
    d2 = ((pred - true) ** 2).sum(-1)  # (N, n) squared distances, mm^2
    surface = d2[:, :n_plane]
    out = {
        "n_contacts": int(len(pred)),
        "all_node_rmse_um": float(np.sqrt(d2.mean()) * 1e3),
        "surface_rmse_um": float(np.sqrt(surface.mean()) * 1e3),
        "interior_rmse_um": float(np.sqrt(d2[:, n_plane: free_layers * n_plane].mean()) * 1e3),
        "relative_error": float(np.sqrt(d2.sum() / max((true**2).sum(), 1e-30))),
    }
    if contact_mask is not None:
        mask = np.asarray(contact_mask, bool)
        out["contact_patch_rmse_um"] = float(np.sqrt(surface[mask].mean()) * 1e3) if mask.any() else float("nan")
        out["contact_nodes"] = int(mask.sum())
    true_depth = -true[:, :n_plane, 2]
    k = true_depth.argmax(1)
    rows = np.arange(len(k))
    deepest = true_depth[rows, k]
    ok = deepest > 0
    rel = (-pred[rows, k, 2][ok] - deepest[ok]) / deepest[ok] * 100.0
    out["deepest_node_error_pct"] = {
        "mean": float(rel.mean()) if rel.size else float("nan"),
        "mean_abs": float(np.abs(rel).mean()) if rel.size else float("nan"),
        "p95_abs": float(np.percentile(np.abs(rel), 95)) if rel.size else float("nan"),
    }
    return out
