"""Multipart form bodies: parsed with limits, fields checked one by one, and their OpenAPI text.

Routes parse multipart bodies themselves (rather than with FastAPI's ``File``/``Form``) so that
file count, field count and part size are bounded before anything is buffered.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

from fastapi import HTTPException, Request
from starlette.datastructures import FormData, UploadFile
from starlette.formparsers import MultiPartException

from service.errors import Refusal

# Plain ASCII digits only: int() would also take "1_000", " 5 " and non-ASCII digits.
DIGITS = re.compile(r"[0-9]{1,19}")
MAX_CALIBRATION_FILE = 1024 * 1024
MAX_TEXT_FIELD = 4 * 1024 * 1024


async def read_form(request: Request, max_files: int, max_fields: int) -> FormData:
    content_type = request.headers.get("content-type", "")
    if not content_type.startswith("multipart/form-data"):
        raise HTTPException(415, "expected a multipart/form-data body")
    try:
        return await request.form(
            max_files=max_files, max_fields=max_fields, max_part_size=MAX_TEXT_FIELD
        )
    except MultiPartException as error:
        raise Refusal(400, f"malformed multipart body: {error.message}", "malformed") from error
    except (ValueError, KeyError) as error:
        raise Refusal(400, f"malformed multipart body: {error}", "malformed") from error


async def file_field(form: FormData, name: str, limit: int | None = None) -> bytes:
    item = form.get(name)
    if item is None:
        raise HTTPException(422, f"missing file field {name!r}")
    if not isinstance(item, UploadFile):
        raise HTTPException(422, f"field {name!r} must be a file upload")
    data = await item.read()
    if limit is not None and len(data) > limit:
        raise HTTPException(413, f"file {name!r} is larger than {limit} bytes")
    return data


def text_field(form: FormData, name: str, required: bool = True) -> str | None:
    item = form.get(name)
    if item is None:
        if required:
            raise HTTPException(422, f"missing form field {name!r}")
        return None
    if not isinstance(item, str):
        raise HTTPException(422, f"form field {name!r} must be text, not a file")
    if "\x00" in item:  # no database text type stores NUL (PostgreSQL refuses it)
        raise HTTPException(422, f"form field {name!r} contains a NUL character")
    return item


def int_field(form: FormData, name: str, low: int, high: int) -> int:
    text = text_field(form, name)
    assert text is not None
    if not DIGITS.fullmatch(text):
        raise HTTPException(
            422, f"form field {name!r} must be a non-negative integer in plain ASCII digits"
        )
    value = int(text)
    if not low <= value <= high:
        raise HTTPException(422, f"form field {name!r} must be in [{low}, {high}]")
    return value


def rate_field(form: FormData, name: str, high: float) -> float | None:
    """An optional positive number field (a rate in Hz); absent or blank is None."""
    text = text_field(form, name, required=False)
    if text is None or not text.strip():
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 < value <= high):
        raise HTTPException(422, f"form field {name!r} must be a number in (0, {high:g}]")
    return value


def json_object_field(form: FormData, name: str) -> dict[str, Any]:
    """An optional JSON object field; absent or blank is ``{}``."""
    text = text_field(form, name, required=False)
    if text is None or not text.strip():
        return {}
    try:
        value = json.loads(text)
    except json.JSONDecodeError as error:
        raise HTTPException(422, f"form field {name!r} is not valid JSON: {error}") from error
    if not isinstance(value, dict):
        raise HTTPException(422, f"form field {name!r} must be a JSON object")
    return value


def multipart_body(required: list[str], properties: dict[str, Any]) -> dict[str, Any]:
    """OpenAPI request body of a multipart route (FastAPI cannot infer it from raw parsing)."""
    schema = {"type": "object", "required": required, "properties": properties}
    return {
        "requestBody": {
            "required": True,
            "content": {"multipart/form-data": {"schema": schema}},
        }
    }


BINARY = {"type": "string", "format": "binary"}
CONFIG_FIELD = {"type": "string", "description": "JSON SwarmvoConfig"}
