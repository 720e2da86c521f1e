"""Dissection track: RopeCutting (``rope_cutting``) and PrecisionCutting (``precision_cutting``); TissueDissection
is not implemented yet."""
