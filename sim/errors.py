"""The one exception type that means "the user asked for something invalid".

Commands turn it into exit code 2 and a single line naming the problem; library code raises it
for bad specs, bad configs and bad paths. It subclasses ValueError so plain Python callers can
catch it the usual way.
"""


class UserError(ValueError):
    """Invalid user input: a spec, a config key, a value out of range, an unusable path."""
