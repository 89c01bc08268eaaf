"""The shot review page: a reconstruction packed into a self-contained WebGL page (``lgi review``).

:mod:`lgi.review.pack` turns arrays into the compact, typed blobs the page reads; :mod:`lgi.jobs.review`
gathers a reconstruction's outputs and writes the page. The viewer itself (``static/``) is plain JavaScript
and WebGL written for lgi: no third-party code, nothing fetched at view time.
"""
