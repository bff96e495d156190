"""`jaxfusion view`: an interactive 3-D web viewer of saved maps (application layer).

`scene_data` computes what is shown (loading, colours, filters) without viser; `server`
serves it with viser (the optional `viewer` extra: `pip install 'jaxfusion[viewer]'`);
`command` is the `view` subcommand. The engine never imports this package.
"""

from jaxfusion.lab.viewer import scene_data

__all__ = ["scene_data"]
