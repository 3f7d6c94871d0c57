"""Stateless maths. Pure-PyTorch references are always importable; accelerated backends load lazily."""
