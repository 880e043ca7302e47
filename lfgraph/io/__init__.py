"""Input: capture layouts (image folders, mosaics, pairs, videos) read lazily frame by frame, and detections made
by other tools."""
