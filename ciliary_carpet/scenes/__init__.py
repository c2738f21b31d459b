"""Scene files: their schema, path rules, parsing, and the objects a scene describes."""
