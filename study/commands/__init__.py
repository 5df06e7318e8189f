"""Command adapters of `hydrabench` (`study.cli` holds the entry point and the argument types).

One module per command family, and nothing but the command line in them: `add_*(sub, name,
help_text)` builds a command's parser, the argparse types that exist only for its options, a
`run*(args)` that turns the parsed options into the experiment's config dataclass or keyword call,
and the text formatting of its result (`emit` prints it, or the JSON object with --json). The work
itself is in the experiments beside this package (`study.engine.train`, `study.engine.gate_training`, `study.eco`, ...),
which never see argparse, and in `study.bench` for the measurements.
"""
