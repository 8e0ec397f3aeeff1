"""Measurements of the model and the node: the one home of benchmark and soak code.

Nothing here is a product path; the model (``supramodal``), the drivers and the node never
import it. Each module is runnable with ``python -m supramodal.benchmarks.NAME`` and prints its report.
"""
