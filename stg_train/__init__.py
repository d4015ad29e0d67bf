"""stg_train: learn Spacetime Gaussians from multi-view video (torch). Depends on stg_runtime."""
