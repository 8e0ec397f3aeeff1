"""Scenes: the schema (one validation vocabulary, one form), the registries of drivers and sinks,
the one builder that turns a scene into a running graph, and a scene's variants made in code."""
