"""EventCap stage that reconstructs intensity images from events alone (event-only cameras: pipeline=events_only)."""
