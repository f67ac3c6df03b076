"""The viewer's S2CamP panel and training-camera frusta."""
