"""The field config tool: `roadwatch` subcommands for installers and maintenance staff."""
