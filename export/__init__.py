"""Training and ONNX export of edgepose's networks (needs the `export` extra: torch, onnx)."""
