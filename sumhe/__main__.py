from sumhe import cli

cli.script()
