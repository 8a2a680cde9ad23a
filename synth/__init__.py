"""Producers of synthetic capture folders and photo sets, with a known answer: closed-form
captures, the Mitsuba 3 corpus, textured photo sets and simulated RAW brackets.

The photo pipeline (capture, reconstruct, appearance, export) never imports this package; only
the command line, the paper-table harness, the tests and the benchmarks do.
"""
