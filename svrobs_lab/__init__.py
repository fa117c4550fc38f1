"""The application layer: the use cases the front ends (REST, web, worker, CLI) call."""
