"""EventCap source stage for recordings from real cameras (and the project's own recording format)."""
