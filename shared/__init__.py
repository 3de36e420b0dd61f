"""SpatialAnt's common library: schemas, codec, key expressions, bus, service runner."""

__version__ = "0.1.0"
