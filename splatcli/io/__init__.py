"""Files: .ply, .splat, checkpoints, images, transforms.json, the one model loader,
export, atomic writes and safe paths."""
