"""Whether bytes taken from a broker queue are a message kombu's consumer can take.

Both transports (``service.file_broker`` and ``service.redis_broker``) check what
they take with :func:`decode_message` before kombu decodes it, and set aside what
fails instead of raising in the worker's loop (docs/security.md#task-messages).
"""

from __future__ import annotations

from typing import Any

from kombu.utils.encoding import bytes_to_str
from kombu.utils.json import loads


def decode_message(channel: Any, data: bytes) -> tuple[Any, str | None]:
    """``(payload, None)`` when ``data`` is a kombu envelope ``channel`` can deliver,
    else ``(None, reason)``: the envelope is decoded and built as the consumer would."""
    try:
        payload = loads(bytes_to_str(data))
        channel.Message(payload, channel=channel)
    except Exception as exc:  # noqa: BLE001 - whatever kombu would raise in the worker's loop
        return None, f"{type(exc).__name__}: {str(exc)[:200]}"
    return payload, None
