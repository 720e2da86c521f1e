"""Dissection track: RopeCutting (``rope_cutting``), PrecisionCutting (``precision_cutting``) and TissueDissection
(``tissue_dissection``)."""
