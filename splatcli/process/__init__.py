"""From a capture to a posed dataset: input detection, one module per input kind
(photos and video, COLMAP workspace, transforms.json), scene bounds, and publishing."""
