"""Running windowvo: the streaming API (``stream.Odometry``), the file pipeline (``pipeline``), the back end
in a worker process (``parallel``), a whole job (``job``) and what it writes (``outputs``)."""
