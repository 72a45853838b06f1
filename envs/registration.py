"""Gymnasium registration of the torchsoil environments (string entry points into `envs/`)."""

from __future__ import annotations

ENV_ID = "torchsoil/SoilTraverse-v0"


def register_envs() -> None:
    """Register `torchsoil/SoilTraverse-v0` (single and vector entry points); idempotent."""
    import gymnasium

    if ENV_ID in gymnasium.registry:
        return
    gymnasium.register(id=ENV_ID, entry_point="envs.soil_traverse:SoilTraverseEnv",
                       vector_entry_point="envs.vector:SoilTraverseVectorEnv")
