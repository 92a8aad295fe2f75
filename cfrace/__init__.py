"""cfrace: multi-agent competitive drone racing for Crazyflies."""

__version__ = "0.1.0"
