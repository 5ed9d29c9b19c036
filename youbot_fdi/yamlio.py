"""YAML reading for every configuration and parameter file: PyYAML's safe loader, in C (libyaml)
when PyYAML has it (an identified parameter file parses about ten times faster)."""
import yaml

SAFE_LOADER = getattr(yaml, 'CSafeLoader', yaml.SafeLoader)


def load_yaml(text):
    """The data of a YAML document (``yaml.safe_load`` semantics)."""
    return yaml.load(text, Loader=SAFE_LOADER)  # noqa: S506 - a safe loader, C or Python
