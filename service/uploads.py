"""Streaming receiver of ``multipart/form-data`` uploads.

The request body is parsed as it arrives and every part is written straight to a file of a
staging directory, so that an upload never sits in memory and a part over the size limit is
refused (413) while it streams, before it is stored. A SHA-256 of every part identifies the
request for idempotency checks.
"""

from __future__ import annotations

import hashlib
from collections.abc import AsyncIterator, Collection
from dataclasses import dataclass, field
from pathlib import Path
from typing import BinaryIO

from python_multipart.exceptions import FormParserError
from python_multipart.multipart import MultipartParser, parse_options_header
from starlette.requests import ClientDisconnect

from pwlreg.service.problems import Problem, invalid_input, malformed_request, upload_too_large

OVERHEAD_BYTES = 64 * 1024
"""Allowance for multipart boundaries and part headers in the whole-request size check."""

SMALL_PART_BYTES = 8 * 1024
"""Limit of each small form field (e.g. a webhook URL), whatever the upload limit."""

DRAIN_LIMIT_BYTES = 16 * 1024 * 1024
"""After a refused part, at most this many further bytes are read (and discarded) so that the
client sees the 413 answer instead of a reset connection; a longer body is cut off."""


@dataclass
class Part:
    """One received part of the form."""

    name: str
    path: Path
    filename: str | None
    size: int = 0
    digest: str = ""


@dataclass
class ReceivedForm:
    """The parts of one request, stored in a staging directory."""

    parts: dict[str, Part] = field(default_factory=dict)

    def fingerprint(self) -> str:
        """SHA-256 over the names and contents of every part, independent of their order."""
        h = hashlib.sha256()
        for name in sorted(self.parts):
            h.update(name.encode() + b"\0" + self.parts[name].digest.encode() + b"\0")
        return h.hexdigest()


class _Receiver:
    """Callbacks of :class:`python_multipart.MultipartParser` writing parts to files."""

    def __init__(
        self,
        staging: Path,
        allowed: Collection[str],
        max_part_bytes: int,
        small_parts: Collection[str] = (),
    ) -> None:
        self.staging = staging
        self.allowed = allowed
        self.max_part_bytes = max_part_bytes
        self.small_parts = small_parts
        self.form = ReceivedForm()
        self.problem: Problem | None = None
        self._header_name = b""
        self._header_value = b""
        self._disposition: bytes | None = None
        self._part: Part | None = None
        self._file: BinaryIO | None = None
        self._hash: hashlib._Hash | None = None

    def callbacks(self) -> dict[str, object]:
        return {
            "on_part_begin": self.on_part_begin,
            "on_part_data": self.on_part_data,
            "on_part_end": self.on_part_end,
            "on_header_field": self.on_header_field,
            "on_header_value": self.on_header_value,
            "on_header_end": self.on_header_end,
            "on_headers_finished": self.on_headers_finished,
        }

    def fail(self, problem: Problem) -> None:
        self.problem = problem
        self.close()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    # -- parser callbacks (a set problem makes them no-ops; the body is then only drained)

    def on_part_begin(self) -> None:
        self._disposition = None
        self._part = None

    def on_header_field(self, data: bytes, start: int, end: int) -> None:
        self._header_name += data[start:end]

    def on_header_value(self, data: bytes, start: int, end: int) -> None:
        self._header_value += data[start:end]

    def on_header_end(self) -> None:
        if self._header_name.strip().lower() == b"content-disposition":
            self._disposition = self._header_value
        self._header_name = b""
        self._header_value = b""

    def on_headers_finished(self) -> None:
        if self.problem is not None:
            return
        if self._disposition is None:
            self.fail(malformed_request("a part of the form has no Content-Disposition header"))
            return
        _, params = parse_options_header(self._disposition)
        raw_name = params.get(b"name")
        if raw_name is None:
            self.fail(malformed_request("a part of the form has no name"))
            return
        name = raw_name.decode("utf-8", "replace")
        if name not in self.allowed:
            self.fail(
                invalid_input(
                    f"unknown form field {name!r}; expected "
                    + ", ".join(sorted(self.allowed)),
                    name,
                )
            )
            return
        if name in self.form.parts:
            self.fail(invalid_input(f"form field {name!r} given twice", name))
            return
        filename = params.get(b"filename")
        self._part = Part(
            name=name,
            path=self.staging / name,
            filename=None if filename is None else filename.decode("utf-8", "replace"),
        )
        self._file = open(self._part.path, "wb")  # noqa: SIM115 (closed in on_part_end/close)
        self._hash = hashlib.sha256()

    def on_part_data(self, data: bytes, start: int, end: int) -> None:
        if self.problem is not None or self._part is None or self._file is None:
            return
        chunk = data[start:end]
        self._part.size += len(chunk)
        limit = (
            min(SMALL_PART_BYTES, self.max_part_bytes)
            if self._part.name in self.small_parts
            else self.max_part_bytes
        )
        if self._part.size > limit:
            self.fail(
                upload_too_large(
                    f"{self._part.name} is larger than the limit of {limit} bytes",
                    self._part.name,
                )
            )
            return
        self._file.write(chunk)
        assert self._hash is not None
        self._hash.update(chunk)

    def on_part_end(self) -> None:
        if self.problem is not None or self._part is None:
            return
        self.close()
        assert self._hash is not None
        self._part.digest = self._hash.hexdigest()
        self.form.parts[self._part.name] = self._part
        self._part = None


async def _until_disconnect(stream: AsyncIterator[bytes]) -> AsyncIterator[bytes]:
    try:
        async for chunk in stream:
            yield chunk
    except ClientDisconnect:
        raise malformed_request("the client disconnected before the end of the body") from None


async def receive_form(
    content_type: str | None,
    content_length: str | None,
    stream: AsyncIterator[bytes],
    staging: Path,
    allowed: Collection[str],
    max_part_bytes: int,
    small_parts: Collection[str] = (),
) -> ReceivedForm:
    """Receive a ``multipart/form-data`` body into ``staging``, one file per part.

    Parameters
    ----------
    content_type, content_length : str or None
        The request headers.
    stream : async iterator of bytes
        The request body.
    staging : pathlib.Path
        Existing empty directory; part ``name`` is written to ``staging / name``.
    allowed : collection of str
        Accepted part names; any other name is refused (422).
    max_part_bytes : int
        Largest accepted part, in bytes (413 above it).
    small_parts : collection of str
        Those of ``allowed`` that are small fields, limited to :data:`SMALL_PART_BYTES`.

    Raises
    ------
    Problem
        415 for another content type, 400 for a malformed body, 413 for a part over the limit
        (or a body whose declared length could not hold only allowed parts under the limit),
        422 for an unknown or repeated part.
    """
    media_type, params = parse_options_header(content_type or "")
    if media_type != b"multipart/form-data":
        raise Problem(
            415,
            "unsupported-media-type",
            "Unsupported media type",
            "the request body must be multipart/form-data with the parts reference, moving "
            "and optionally points and options",
        )
    boundary = params.get(b"boundary")
    if not boundary:
        raise malformed_request("multipart/form-data without a boundary parameter")
    small = [name for name in allowed if name in small_parts]
    limit_total = (
        (len(allowed) - len(small)) * max_part_bytes
        + len(small) * min(SMALL_PART_BYTES, max_part_bytes)
        + OVERHEAD_BYTES
    )
    if content_length is not None:
        try:
            declared = int(content_length)
        except ValueError:
            raise malformed_request("Content-Length is not a number") from None
        if declared > limit_total:
            raise upload_too_large(
                f"the request body ({declared} bytes) is larger than the limit of "
                f"{limit_total} bytes ({max_part_bytes} bytes per part)"
            )
    receiver = _Receiver(staging, allowed, max_part_bytes, small_parts)
    try:
        parser = MultipartParser(boundary, receiver.callbacks())  # type: ignore[arg-type]
    except FormParserError as exc:
        raise malformed_request(f"invalid multipart boundary: {exc}") from None
    drained = 0
    try:
        async for chunk in _until_disconnect(stream):
            if receiver.problem is None:
                try:
                    parser.write(chunk)
                except FormParserError as exc:
                    receiver.fail(malformed_request(f"malformed multipart body: {exc}"))
            else:
                drained += len(chunk)
                if drained > DRAIN_LIMIT_BYTES:
                    break
        if receiver.problem is None:
            try:
                parser.finalize()
            except FormParserError as exc:
                receiver.fail(malformed_request(f"malformed multipart body: {exc}"))
    finally:
        receiver.close()
    if receiver.problem is not None:
        raise receiver.problem
    if receiver._part is not None:
        raise malformed_request("the multipart body ended in the middle of a part")
    return receiver.form
