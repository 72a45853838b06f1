"""Gymnasium environments on the torchsoil simulator (registered by
`torchsoil.registration.register_envs`)."""
