"""Validation of JSON messages against the package's schemas (generated from the Rust types)."""

from __future__ import annotations

from typing import Any, Mapping

import jsonschema

from ebmpc import wire


def validate(name: str, message: Mapping[str, Any]) -> None:
    """Raises ``jsonschema.ValidationError`` unless ``message`` is a valid ``name`` message."""
    schema = wire.schema(name)
    validator = jsonschema.validators.validator_for(schema)
    validator.check_schema(schema)
    validator(schema).validate(message)
