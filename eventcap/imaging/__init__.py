"""Images: sharp latent images from frames and events (EDI), images from events alone, the rasteriser of the
synthetic camera, and pictures of recordings for people. Domain library: no orchestration."""
