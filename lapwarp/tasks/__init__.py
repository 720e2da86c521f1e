"""Task envs, one module per task, grouped by the paper's tracks (spatial, deformable, dissection, thread)."""
