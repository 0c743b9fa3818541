"""Hydra plugin: every installed stage's config dataclass is a structured config ``/stage/<name>`` (and the run's
outputs and executor settings ``/settings/outputs``, ``/settings/executor``) wherever Hydra
composes EventCap's configs (``eventcap run``, sweeps, launchers, ``hydra.compose`` in scripts and tests), so a
stage variant's YAML can start from its spec's defaults and state only what differs
(:func:`eventcap.core.config.register_stage_configs`). Every installed package's own config folder (its pipelines
and stage variants, declared by an ``eventcap.configs`` entry point: :func:`eventcap.core.registry.plugin_config_dirs`)
goes on the search path after the project's ``conf/``, so a plugin adds nodes without editing the project's files."""

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class EventcapStageConfigs(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        # Called before every composition: the stage configs are in the ConfigStore by the time a config names them.
        from eventcap.apps.output_settings import OutputsConfig
        from eventcap.core.config import register_settings_configs, register_stage_configs
        from eventcap.core.registry import plugin_config_dirs
        from eventcap.core.runner import ExecutorConfig

        register_stage_configs()
        register_settings_configs({"outputs": OutputsConfig, "executor": ExecutorConfig})
        for provider, folder in plugin_config_dirs():
            search_path.append(provider=provider, path=f"file://{folder}")
