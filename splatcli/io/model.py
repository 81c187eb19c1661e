"""Transitional: the model loader is splatcli/model.py (it opens projects, and io/ knows
none). eval/evaluate.py and train/init.py, being changed elsewhere, still import it
from here; once they import splatcli.model, delete this module."""

from ..model import LoadedModel, load_model

__all__ = ["LoadedModel", "load_model"]
