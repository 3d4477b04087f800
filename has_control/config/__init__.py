"""Configuration: ``ros__parameters`` YAML files into the core's typed parameters.

``yaml_safe`` reads YAML as a parameter file needs it; ``params_file`` matches
sections to nodes as rcl does; ``schema`` checks every key and builds a
:class:`~has_control.core.params.Config`; ``scenario_files`` reads scenario
sets; ``table`` holds each component's parameter facts (:class:`Param`);
``gains_file`` writes tuned gains as a ``--params-file``.
"""
from has_control.config.gains_file import gains_params_yaml, write_gains_params  # noqa: F401
from has_control.config.params_file import (  # noqa: F401
    LIBRARY_NODES, MAX_CONFIG_BYTES, node_matches, read_parameter_file, read_parameter_files,
)
from has_control.config.scenario_files import (  # noqa: F401
    MAX_SCENARIOS, SCENARIO_PREFIXES, Scenario, check_scenarios, load_scenarios, scenario_configs, scenarios_from_json,
)
from has_control.config.schema import (  # noqa: F401
    CONFIG_DIR, CONFIG_TABLE, GAIN_MAX, MAX_SAMPLES, SEED_LIMIT, SEED_RANGE, build_config, check_gain,
    config_parameters, default_config_files, finite_number, is_seed, load_config, with_horizon,
)
from has_control.config.table import Param, refusal, table, yaml_with_comments  # noqa: F401
from has_control.config.yaml_safe import MAX_YAML_DEPTH, flatten, load_yaml  # noqa: F401
