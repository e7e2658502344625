"""The CSA service: FastAPI app, database, artifact store, job worker (see ``create_app``)."""
