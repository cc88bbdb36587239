"""Quasi-static linear-elastic FEM of the pad with rigid-indenter contact."""
