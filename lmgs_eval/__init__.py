"""lmgs_eval: the evaluation toolkit (subjects, metrics, protocols, results, tables, CLI)."""

__version__ = "0.1.0"
