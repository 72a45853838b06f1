"""Estimation (paper section V): the soil's parameters fitted window by window along a drive.

Modules: `windows` (the path index and each window's ground and data), `estimator` (the
sliding-window estimator over a terrain pair), `optimizer` (projected gradient descent with
bounds), `cost` (the weighted L1 cost), `nuisance` (the map offset between H_f and H_b),
`visits` (ground driven more than once: wheel passes, per-visit rows), `live` (windows fitted as
a recording streams through the pipeline), `tiles` (the simulated change stitched over windows
in bounded memory), `outputs` (params.csv, reference.csv, TensorBoard, simulated.npz,
passes.npz) and `figures` (Fig. 4, Fig. 6, the multi-pass figures, summary.md).
"""

from torchsoil.estimate.estimator import Estimator, Stitcher, WindowOutput

__all__ = ["Estimator", "Stitcher", "WindowOutput"]
