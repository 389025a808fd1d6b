"""Benchmarks behind ``swarmvo bench NAME``: each prints a table and writes JSON/PNG."""
