"""``/filters``: the moving-average and Kalman filters (``{"Q": .., "R": ..}``, ``{"samples": ..}``)."""

from .blocks import block_router

router = block_router("filter", "/filters", [{"Q": 4e-6, "R": 1e-4}, {"samples": 30}])
