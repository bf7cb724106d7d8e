"""Motion-type classifier for DOCT maps (placeholder, completed below)."""
__version__ = "0.1.0"
