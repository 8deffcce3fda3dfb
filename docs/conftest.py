"""pytest collects the Markdown pages of docs/ (their Python blocks run, through
pytest-markdown-docs), not the executed notebook copies (notebooks/ runs the
notebooks themselves) or the build's hooks and scripts."""

collect_ignore_glob = ["notebooks/*", "ext/*", "benchmarks/*"]
