"""Configuration plumbing: OmegaConf resolvers (run directories under torchrun) and the runtime settings every
experiment shares (debug shrinking, device, threads, precision, seed, logging)."""
from pathlib import Path

# The configs: codesign/conf, a link to the repository's top-level conf/ in a checkout (an editable install) and a
# copy of it inside an installed wheel; one place for the entry point, the API and the config reference to find them.
CONF_DIR = Path(__file__).resolve().parents[1] / "conf"
