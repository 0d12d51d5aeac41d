"""Workflows: several pipeline steps run as one job (synthesise -> train -> evaluate ->
report).
"""
