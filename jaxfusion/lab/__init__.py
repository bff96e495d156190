"""jaxfusion.lab: the application built on the library — every command, protocol, study,
figure, report writer, front-end cache and the viewer.

The library (`jaxfusion`) never imports this package; it imports the library and the networks
(`jaxfusion_models`). `jaxfusion.lab.cli.main` is the `jaxfusion` command.
"""
