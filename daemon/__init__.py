"""The boat daemon (``seamap run``): drivers, core and publishers wired under asyncio."""
