"""The data side: scenes read and checked (COLMAP models, transforms.json, images), the S2CamP data parser, and
nerfstudio cameras converted to and from the core's."""
