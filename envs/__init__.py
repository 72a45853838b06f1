"""Gymnasium environments on the torchsoil simulator, registered on import (`register_envs`).

`torchsoil/SoilTraverse-v0`: `envs.soil_traverse.SoilTraverseEnv` and the batched
`envs.vector.SoilTraverseVectorEnv`, thin classes over the pure functions of `envs.core`
with the static parameters of `envs.params` (settings: `torchsoil.settings.EnvConfig`).
"""

from envs.registration import ENV_ID, register_envs

__all__ = ["ENV_ID", "register_envs"]

register_envs()
