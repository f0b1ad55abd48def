"""Fields: the Field and Expert contracts (`base`), the expert families (`dvgo`, `tensorf`, `ngp`) and
the grids and MLPs they are built from. `registry` names the families. Maths and modules only: files
are read and written by `boostnerf_cli.models`.

This file imports nothing, so that `fields.base` (the contract the renderer needs) loads alone.
"""
