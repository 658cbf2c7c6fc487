"""The `roadwatch` command: one click group whose subcommands live in their own modules."""

# Subcommands are imported only when used, so `roadwatch --help` is fast and a broken optional
# module cannot stop the others.

from __future__ import annotations

import importlib
import os
import sys

import click

# name -> (module, attribute, one-line help). Each module defines a click.Command.
COMMANDS: dict[str, tuple[str, str, str]] = {
    "demo": ("tools.demo_cmd", "demo", "Run the service on the embedded demo site (no camera needed)."),
    "run": ("tools.service_cmd", "run", "Run the detector service from a config file."),
    "simulate": ("tools.simulate.cli", "simulate", "Render a synthetic traffic scene with exact ground truth."),
    "replay": ("tools.replay", "replay", "Run the pipeline on a video file or image sequence."),
    "evaluate": ("tools.evaluate", "evaluate", "Compare results with ground truth or hand counts."),
    "site-from-counts": ("tools.handcount", "site_from_counts", "Make a site config from a hand-count file."),
    "counts-from-sim": ("tools.counts_from_sim", "counts_from_sim",
                        "Write a simulated scene as a hand-counted clip (frames and counts.json)."),
    "bench": ("tools.bench", "bench", "Measure frames per second per core and memory."),
    "sweep": ("tools.sweep", "sweep", "Simulate, replay and evaluate many scenes: the accuracy targets' table."),
    "clip-variants": ("tools.clip_variants", "clip_variants",
                      "Replay a hand-counted clip changed the ways other footage differs; counts per variant."),
    "install": ("tools.install", "install", "Install the service on this box (systemd unit, config, dirs)."),
    "uninstall": ("tools.install", "uninstall", "Remove the service from this box."),
    "selftest": ("tools.selftest", "selftest", "Prove this box works end to end on a synthetic scene."),
    "registers": ("tools.registers_cmd", "registers", "Print the Modbus register map for a config."),
    "snapshot": ("tools.fieldtool.snapshot", "snapshot", "Grab a frame from the source or service to PNG."),
    "calibrate": ("tools.fieldtool.calibrate", "calibrate", "Compute the camera calibration and draw a grid."),
    "zones": ("tools.fieldtool.zones", "zones", "Define and draw lanes, zones, fiducials and loops."),
    "config": ("tools.fieldtool.config_cmd", "config", "Validate, show, diff and apply configs."),
    "status": ("tools.fieldtool.status", "status", "Show health and live counts of the running service."),
    "test-call": ("tools.fieldtool.testcall", "test_call", "Force a detector call for cabinet tests."),
    "export": ("tools.fieldtool.export", "export", "Export periods, loop events or vehicles from the store."),
    "report": ("tools.fieldtool.report", "report", "Plot flow/speed/occupancy and a time-space diagram."),
}


class LazyGroup(click.Group):
    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module, attr, _ = COMMANDS[name]
        try:
            return getattr(importlib.import_module(module), attr)
        except (ImportError, AttributeError) as e:

            @click.command(name=name, help=COMMANDS[name][2])
            def unavailable() -> None:
                raise click.ClickException(f"'{name}' is not available in this build ({e})")

            return unavailable

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        rows = [(n, COMMANDS[n][2]) for n in self.list_commands(ctx)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


def _default_numba_cache() -> None:
    # numba raises at import when it cannot write its cache next to read-only site-packages.
    if "NUMBA_CACHE_DIR" not in os.environ:
        base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        os.environ["NUMBA_CACHE_DIR"] = os.path.join(base, "roadwatch", "numba")


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="roadwatch")
def cli() -> None:
    """Roadwatch: a roadside video vehicle detector.

    \b
    Quick start (no camera needed):
      roadwatch demo --seconds 60
    """


def main() -> None:
    _default_numba_cache()
    sys.exit(cli.main(prog_name="roadwatch"))


if __name__ == "__main__":
    main()
