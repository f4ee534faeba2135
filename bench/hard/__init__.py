"""The hard-case suite (issue 22): lighting objcam's bench never saw, rendered by a scene it did not write.

``python -m bench.hard`` (``make bench BENCH=hard``); bench/hard/design.py says which cases and why.
"""
