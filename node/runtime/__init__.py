"""The node at run time: sources and their rings and clocks, streams, fusion, events, sinks and taps.

The only part of the package with threads and buffers.
"""
