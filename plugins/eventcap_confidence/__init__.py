"""Stage confidence: how much of the estimated motion was seen (eventcap.analysis.confidence)."""
