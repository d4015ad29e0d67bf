# Import stg_train before any test module imports torch, so its OpenMP setting takes effect
# (see stg_train/__init__.py).
import stg_train  # noqa: F401
