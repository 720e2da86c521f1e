"""Dissection track: RopeCutting (``rope_cutting``); PrecisionCutting and TissueDissection are not implemented yet."""
