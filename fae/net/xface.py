"""The Xface toolkit's player protocol: task framing, task parsing, notify bytes.

Pure codec, no sockets: :class:`TaskSplitter` cuts a byte stream into task messages,
:func:`parse_task` reads one, :func:`notify_bytes` writes a reply exactly as Xface does
(see docs/protocol.md and the standard's reference notes on Xface).
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass

# Notification status codes (Xface sends 0, 1, 2, 3 and 7).
STATUS_UNKNOWN = 0
STATUS_QUEUED = 1
STATUS_STARTED = 2
STATUS_FINISHED = 3
STATUS_ERROR = 7

_END_TAG = b"</task>"
MAX_ELEMENTS = 256  # per task: a task and its <param>s (tasks carry a handful)
MAX_NAME = 64  # task names are short words (UPLOAD_FAP)
MAX_ID_DIGITS = 10  # ownerId and taskId are C ints in Xface
_ID_RE = re.compile(r"[+-]?[0-9]{1,%d}\Z" % MAX_ID_DIGITS)


class TaskFormatError(ValueError):
    """A message that is not a `<task name=".." ownerId=".." taskId="..">` element."""


@dataclass(frozen=True)
class XfaceTask:
    """One client request.

    name      task name, e.g. "UPLOAD_FAP"
    owner_id  client id the replies are routed to (0: only the queued ack is sent)
    task_id   the client's own number for this task, echoed in replies
    params    the text of each `<param>` element, as written
    """

    name: str
    owner_id: int
    task_id: int
    params: tuple[str, ...]


def notify_bytes(name: str, owner_id: int, task_id: int, status: int) -> bytes:
    """The reply for one task state: the XML element and two NUL bytes, no newline."""
    return f'<notify name="{name}" ownerId="{owner_id}" taskId="{task_id}" status="{status}"/>'.encode("utf-8") + b"\0\0"


def error_notify_bytes() -> bytes:
    """The reply to an unknown task name or a message that is not a task."""
    return notify_bytes("ERROR", 0, 0, STATUS_ERROR)


def parse_task(message: bytes) -> XfaceTask:
    """Read one task message (without its NUL terminators).

    Raises TaskFormatError naming what was expected when the message is not UTF-8, not
    XML, not a `task` element, or lacks a name or an integer ownerId/taskId.
    """
    try:
        text = message.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise TaskFormatError(f"byte {exc.start}: expected UTF-8 text") from None
    if "<!DOCTYPE" in text:  # entities are declared there: a few MiB could expand to gigabytes
        raise TaskFormatError("expected a <task> element without a <!DOCTYPE> (no tasks declare entities)")
    # a task holds a few <param>s: 8 MiB of 2 million empty elements took the parser 0.65 s
    # (the server's loop with it: every other client waited) and 55 MB each in the queue
    tags = text.count("<")
    if tags > 2 * MAX_ELEMENTS:
        raise TaskFormatError(f"expected a <task> of at most {MAX_ELEMENTS} elements, got about {tags // 2}")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise TaskFormatError(f"expected a well-formed <task> element ({exc})") from None
    if root.tag != "task":
        raise TaskFormatError(f"expected a <task> element, got <{root.tag}>")
    name = root.get("name")
    if not name:
        raise TaskFormatError('<task>: expected a name="..." attribute')
    if len(name) > MAX_NAME:
        raise TaskFormatError(f'<task>: expected a name of at most {MAX_NAME} characters, got {len(name)}')
    ids = []
    for attr in ("ownerId", "taskId"):
        raw = root.get(attr, "0").strip()
        if not _ID_RE.match(raw):
            shown = raw if len(raw) <= 20 else f"{raw[:20]}... ({len(raw)} characters)"
            raise TaskFormatError(f'<task name="{name}">: expected {attr} as an integer of at most '
                                  f'{MAX_ID_DIGITS} digits, got {shown!r}')
        ids.append(int(raw))
    params = tuple(p.text or "" for p in root.findall("param"))
    return XfaceTask(name=name, owner_id=ids[0], task_id=ids[1], params=params)


def _self_closed_end(buf: bytearray) -> int | None:
    """Where a message that is one self-closing `<task .../>` ends (just after its `/>`), or
    None: the buffer does not start with such an element (after blanks), or its start tag
    is not complete yet. Quoted attribute values may hold `>`. (Such a task without a NUL
    after it was never answered, and the next task's bytes were read as junk after it.)"""
    i = 0
    while i < len(buf) and buf[i] in b" \t\r\n":
        i += 1
    if buf[i:i + 5] != b"<task" or len(buf) <= i + 5 or buf[i + 5] not in b" \t\r\n/":
        return None
    quote = None
    for j in range(i + 5, min(len(buf), i + 4096)):  # a start tag's attributes are short
        c = buf[j]
        if quote is not None:
            if c == quote:
                quote = None
        elif c in b"\"'":
            quote = c
        elif c == ord(">"):
            return j + 1 if buf[j - 1] == ord("/") else None
    return None


class TaskSplitter:
    """Cut a byte stream into task messages.

    A message ends at a NUL byte or right after `</task>` (or the `/>` of a self-closing
    `<task .../>`), whichever comes first, so tasks ending in one NUL, two NULs or nothing
    at all are all found, and a read may hold several tasks or part of one. Empty and
    whitespace-only pieces are skipped.
    :meth:`skip` passes over raw bytes that follow a task (UPLOAD_WAV's audio).

    max_message  bytes one message may hold; a longer one raises TaskFormatError (the
                 caller should close the connection: the stream cannot be resynchronized
                 cheaply) and the buffer is dropped, so memory stays bounded.
    """

    def __init__(self, max_message: int = 8 << 20) -> None:
        self.max_message = int(max_message)
        self._buf = bytearray()
        self._scan_from = 0
        self._skip = 0
        self._skip_nuls = 0

    @property
    def buffered(self) -> int:
        """Bytes held waiting for the end of a message."""
        return len(self._buf)

    @property
    def skipping(self) -> int:
        """Raw bytes still to be passed over (see :meth:`skip`)."""
        return self._skip

    def push(self, data: bytes) -> None:
        """Add bytes (take the messages with :meth:`pop`)."""
        self._buf += data
        self._drop_skipped()

    def skip(self, count: int) -> None:
        """Pass over the next `count` raw bytes of the stream, after at most two NULs ending
        the task before them; no message is looked for inside them."""
        if count < 0:
            raise ValueError(f"skip: expected a byte count >= 0, got {count}")
        self._skip, self._skip_nuls = int(count), 2
        self._scan_from = 0
        self._drop_skipped()

    def _drop_skipped(self) -> None:
        while self._skip_nuls and self._buf[:1] == b"\0":
            del self._buf[:1]
            self._skip_nuls -= 1
        if self._buf:
            self._skip_nuls = 0
        if self._skip and self._buf:
            n = min(self._skip, len(self._buf))
            del self._buf[:n]
            self._skip -= n

    def pop(self) -> bytes | None:
        """The next complete message, or None until more bytes arrive."""
        while not self._skip:
            start = max(0, self._scan_from - len(_END_TAG))
            nul = self._buf.find(b"\0", start)
            end = self._buf.find(_END_TAG, start)
            closed = _self_closed_end(self._buf)
            if closed is not None and (nul < 0 or closed <= nul) and (end < 0 or closed <= end):
                cut, skip = closed, 0
            elif end >= 0 and (nul < 0 or end < nul):
                cut, skip = end + len(_END_TAG), 0
            elif nul >= 0:
                cut, skip = nul, 1
            else:
                self._scan_from = len(self._buf)
                if len(self._buf) > self.max_message:
                    self._buf.clear()
                    self._scan_from = 0
                    raise TaskFormatError(f"expected a task of at most {self.max_message} bytes")
                return None
            piece = bytes(self._buf[:cut])
            del self._buf[: cut + skip]
            self._scan_from = 0
            if len(piece) > self.max_message:
                raise TaskFormatError(f"expected a task of at most {self.max_message} bytes")
            if piece.strip():
                return piece
        return None

    def feed(self, data: bytes) -> list[bytes]:
        """Add bytes; return the complete messages now available, in order."""
        self.push(data)
        out: list[bytes] = []
        while (message := self.pop()) is not None:
            out.append(message)
        return out
