"""Thread Manipulation track: ThreadInHole (``thread_in_hole``); RopeThreading and LigatingLoop are not
implemented yet."""
