"""The explorer's web layer: the Starlette app (:mod:`.server`), one tab's websocket
(:mod:`.session`), who may talk to the server and size limits (:mod:`.guard`), request values
(:mod:`.inputs`), deadlines and a cap on connections (:mod:`.serving`) and starting the server
(:mod:`.launch`).
"""
