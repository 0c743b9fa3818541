"""Hybrid pose batch optimisation (paper Sec. 3.2, Eq. 3-8): all skeleton poses of a batch, jointly, with IPOPT."""
