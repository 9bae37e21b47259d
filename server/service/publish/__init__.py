"""The publisher thread's part: put each tick's bytes, with the replies before and after
(``publisher``), and the 1.5 keyframe queries that mark its predictive streams (``keyframes``,
on Zenoh's threads)."""

__all__ = ["keyframes", "publisher"]
