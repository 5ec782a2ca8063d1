"""Training-free Yin-Yang encoder and Gaussian head in torch, exported to ONNX."""
