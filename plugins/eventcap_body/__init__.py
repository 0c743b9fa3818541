"""The person's body from the detections (the node ``body``; not in the paper, which scanned each actor)."""
