"""What the two HTTP front ends share, below both: the FastAPI dependencies that read
the app's state (settings, DB sessions, the unit publisher, the broker check) and
find the caller of a request (docs/architecture.md#layers). ``service.api`` and
``service.web`` import this package, never each other."""
