"""Configuration: the schema and the loader."""

from appliance.config.loader import load_config, parse_config
from appliance.config.schema import AppConfig

__all__ = ["AppConfig", "load_config", "parse_config"]
