"""EventCap stage that sharpens the blurry intensity frames with the events (EDI, paper Sec. 3.1, Eq. 2)."""
