"""Dissection track: RopeCutting, PrecisionCutting, TissueDissection (not implemented yet)."""
