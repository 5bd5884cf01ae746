"""Processing stages: decode, assemble, filter, mesh, texture, export (one module each)."""
