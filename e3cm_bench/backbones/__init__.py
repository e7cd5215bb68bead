"""The CNN backbones: their names (torch-free), how each is built and tapped, and loading them."""
