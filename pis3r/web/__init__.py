"""The pis3r web page and HTTP API (``pis3r serve``; :func:`pis3r.web.app.create_app`).

Needs the ``web`` extra (FastAPI, uvicorn, python-multipart); nothing here is imported
by the rest of pis3r until the page is served.
"""
