"""Effects layer: whole effects as `equinox.Module` parameter sets, their presets and their JSON form."""
