"""EventCap stages that make recordings: actor templates and the synthetic (simulated) event-camera capture."""
