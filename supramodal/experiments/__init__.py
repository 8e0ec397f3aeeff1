"""The paper's experiments, as functions that return plain data (dicts of numbers).

Printing, files and plots are the CLI's job (see :mod:`supramodal.experiments.report`).
"""
