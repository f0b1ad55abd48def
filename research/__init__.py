"""Experiments behind docs/results.md, outside the boostnerf package (research/README.md lists each question).

A package only so that research/tests imports the scripts by name; each script runs as `python research/NAME.py`.
"""
