"""Scenes: the schema, the registries of drivers and sinks, the builder, and a scene's variants made in code.

The schema is one validation vocabulary, one form; the builder is the one that turns a scene into a
running graph.
"""
