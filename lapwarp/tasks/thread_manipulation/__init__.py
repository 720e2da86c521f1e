"""Thread Manipulation track: ThreadInHole (``thread_in_hole``), RopeThreading (``rope_threading``), LigatingLoop
(``ligating_loop``, with the loop's closing mechanism in ``loop_closure``)."""
