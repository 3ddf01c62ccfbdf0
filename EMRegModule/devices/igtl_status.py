"""OpenIGTLink STATUS message, built on pyigtl's own message base class.

pyigtl (0.3) has TRANSFORM, IMAGE, STRING, POINT, POSITION, POLYDATA but no STATUS. The body,
per the OpenIGTLink protocol specification ("Status Message", protocol version 1-3):

====== ============== =====================================================================
C      uint16         status code (table below)
S      int64          sub-code, device specific
E      char[20]       error name ("OK", "Error", ...), zero padded
M      char[n]        status message, n = body size - 30; EMReg sends it zero terminated
====== ============== =====================================================================

All numbers big-endian like every OpenIGTLink field. :func:`register_status_message` adds the
class to pyigtl's table of message types, so pyigtl's own parser (its clients and servers, and
``MessageBase.create_message``) decodes STATUS messages into :class:`StatusMessage`.
"""

from __future__ import annotations

import struct

from pyigtl import messages as _pyigtl_messages
from pyigtl.messages import MessageBase

#: OpenIGTLink status codes (specification, "Status codes").
STATUS_INVALID = 0
STATUS_OK = 1
STATUS_UNKNOWN_ERROR = 2
STATUS_PANIC = 3
STATUS_NOT_FOUND = 4
STATUS_ACCESS_DENIED = 5
STATUS_BUSY = 6
STATUS_TIME_OUT = 7  # time out / connection lost
STATUS_OVERFLOW = 8  # overflow / can't be reached
STATUS_CHECKSUM_ERROR = 9
STATUS_CONFIG_ERROR = 10
STATUS_RESOURCE_ERROR = 11
STATUS_UNKNOWN_INSTRUCTION = 12
STATUS_NOT_READY = 13
STATUS_MANUAL_MODE = 14
STATUS_DISABLED = 15
STATUS_NOT_PRESENT = 16
STATUS_UNKNOWN_VERSION = 17
STATUS_HARDWARE_FAILURE = 18
STATUS_SHUT_DOWN = 19

ERROR_NAME_LENGTH = 20
_HEADER = struct.Struct("> H q 20s")


class StatusMessage(MessageBase):
    """OpenIGTLink STATUS: ``code`` (uint16), ``subcode`` (int64), ``error_name`` (<= 20 bytes),
    ``status_message`` (text)."""

    def __init__(self, code: int = STATUS_OK, subcode: int = 0, error_name: str = "", status_message: str = "",
                 timestamp: float | None = None, device_name: str | None = None) -> None:
        MessageBase.__init__(self, timestamp=timestamp, device_name=device_name)
        self._message_type = "STATUS"
        if not 0 <= int(code) <= 0xFFFF:
            raise ValueError(f"STATUS code must fit in uint16, got {code}")
        encoded_name = error_name.encode("ascii", errors="replace")
        if len(encoded_name) > ERROR_NAME_LENGTH:
            raise ValueError(f"STATUS error name is at most {ERROR_NAME_LENGTH} bytes, got {error_name!r}")
        self.code = int(code)
        self.subcode = int(subcode)
        self.error_name = error_name
        self.status_message = status_message
        self._valid_message = True

    def content_asstring(self) -> str:
        return (f"Code: {self.code}\nSubcode: {self.subcode}\nError name: {self.error_name}\n"
                f"Message: {self.status_message}")

    def _pack_content(self) -> bytes:
        name = self.error_name.encode("ascii", errors="replace")
        return _HEADER.pack(self.code, self.subcode, name) + self.status_message.encode("utf-8") + b"\0"

    def _unpack_content(self, content: bytes) -> None:
        code, subcode, name = _HEADER.unpack(content[:_HEADER.size])
        self.code = code
        self.subcode = subcode
        self.error_name = name.split(b"\0", 1)[0].decode("ascii", errors="replace")
        self.status_message = content[_HEADER.size:].split(b"\0", 1)[0].decode("utf-8", errors="replace")
        self._valid_message = True


def register_status_message() -> None:
    """Make pyigtl's parser create :class:`StatusMessage` for STATUS messages (idempotent)."""
    _pyigtl_messages.message_type_to_class_constructor.setdefault("STATUS", StatusMessage)


register_status_message()
