"""The report of a study (`build`: report.html from report.json, with its `bounds` and `crossover`
sections), the generated verdict (`verdict`) and the figures (`plots`)."""
