"""Event-based pose refinement (paper Sec. 3.3, Eq. 9-13): silhouette-to-event ICP per tracking frame, with IPOPT."""
