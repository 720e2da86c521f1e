"""Thread Manipulation track: ThreadInHole, RopeThreading, LigatingLoop (not implemented yet)."""
