"""svrobs service: the REST API, DB models and broker configuration shared with the worker."""
