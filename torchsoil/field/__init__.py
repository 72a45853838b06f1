"""A field across sessions: each recording registered onto the field's frame, its visits and
wheel passes continuing the field's (torchsoil.field.store), by the registration of
torchsoil.field.register."""
