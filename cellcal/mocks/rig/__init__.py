"""The camera rig's twins: the rendered scenes and the GigE Vision cameras that serve them."""
