"""Replay driver: recorded sessions, WAV files and in-memory arrays, as a live driver would deliver them."""
