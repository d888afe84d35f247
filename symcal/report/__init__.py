"""Presenters: text and JSON reports, figures, HTML, the fleet summary."""
