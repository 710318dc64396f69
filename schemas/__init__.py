"""The wire contract shared by every cellsight process: messages, key expressions, codecs, bus.

``drivers``, ``estimator`` and ``recognition`` meet only here (docs/architecture.md section 2).
"""

from schemas.errors import SchemaError

__all__ = ["SchemaError"]
