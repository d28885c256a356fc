"""Experiments: each a module that reproduces a paper's result on the emulated cell."""
