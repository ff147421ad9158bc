"""Files -> prepared cases: reading, closed genus-0 surfaces, bijective sphere maps, the cache."""

from .batch import preprocess
from .case import PreparedCase, Rejection, prepare_case

__all__ = ["PreparedCase", "Rejection", "prepare_case", "preprocess"]
