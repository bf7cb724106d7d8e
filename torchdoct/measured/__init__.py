"""Measured (or rendered) sequences: readers and writers (io), computational resolution
reduction (resolution), DOCT maps (maps) and the paper's statistics across samples (compare).
"""
