"""The streaming node: drivers -> ring buffers -> model blocks -> sinks, wired by scene. The only place with threads."""
