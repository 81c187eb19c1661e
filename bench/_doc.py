"""bench/step.py's name for `write_section` (bench/common.py): delete once step.py imports it from common."""

from common import write_section

__all__ = ["write_section"]
