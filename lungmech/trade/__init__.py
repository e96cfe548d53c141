"""The speed–accuracy trade: every model of a scene measured on the same points, side by side."""
