"""The web UI's pages, one router per concern."""
