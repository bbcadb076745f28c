"""A campaign's report, read through the store: the campaign list, the report folder, its
data, figures and page."""
