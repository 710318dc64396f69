"""The ``cellsight`` commands, a module per group; ``cellsight.cli`` is the app that holds them."""
