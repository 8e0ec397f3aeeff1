"""Offline work on recordings: training, fused training, fit, manifests, labels, imports and reports.

No threads: the command line calls these.
"""
