"""Scenes: the schema (one validation vocabulary, one form), the registries of drivers and sinks,
and the one builder that turns a scene into a running graph."""
