"""Camera motion from the pictures."""
