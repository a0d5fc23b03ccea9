"""seamap: georeferenced seabed mosaics from a forward-looking sonar and a Pixhawk."""

__version__ = "0.1.0"
