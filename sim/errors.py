"""The one exception type that means "the user asked for something invalid", and the one that
means "the process was told to stop" (SIGTERM).

Commands turn a UserError into exit code 2 and a single line naming the problem; library code raises
it for bad specs, bad configs and bad paths. It subclasses ValueError so plain Python callers can
catch it the usual way. `Terminated` subclasses KeyboardInterrupt, so every clean-up written for
Ctrl-C (partial shards removed, locks released, workers stopped) runs for a SIGTERM too.
"""


class UserError(ValueError):
    """Invalid user input: a spec, a config key, a value out of range, an unusable path."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised where Ctrl-C raises KeyboardInterrupt (`study.cli.main` installs the handler)."""
