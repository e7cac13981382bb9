MODULE CellctlLogger
    !========================================================================
    ! cellctl logger: runs in a background task beside CellctlServer.mod.
    ! Streams, every cellctlLogPeriod seconds, alternately
    !   "# 0 date time t x y z q1 q2 q3 q4"   (tool in work object, mm)
    !   "# 1 date time t j1 j2 j3 j4 j5 j6"    (degrees, mm for linear axes)
    ! each ended by a newline (the public LOGGER.mod sends none), and reads
    ! "97 #" from the same client: the stop request for the move in progress.
    !========================================================================

    ! Shared with CellctlServer (initial values are set there)
    PERS tooldata cellctlTool;
    PERS wobjdata cellctlWobj;
    PERS bool cellctlStopRequest;
    PERS string cellctlIp;

    PERS num cellctlLoggerPort := 5001;
    PERS num cellctlLogPeriod := 0.01;  ! 0.1 on a virtual controller
    PERS string cellctlMotionTask := "T_ROB1";

    CONST string NL := "\0A";

    VAR socketdev serverSocket;
    VAR socketdev clientSocket;

    PROC main()
        VAR robtarget pose;
        VAR jointtarget joints;
        VAR string head;
        VAR string date;
        VAR string time;
        VAR clock timer;

        date := CDate();
        time := CTime();
        ClkReset timer;
        ClkStart timer;
        SocketCreate serverSocket;
        SocketBind serverSocket, cellctlIp, cellctlLoggerPort;
        SocketListen serverSocket;
        SocketAccept serverSocket, clientSocket \Time:=WAIT_MAX;

        WHILE TRUE DO
            ! A line is longer than one RAPID string (80 characters): send it in parts.
            pose := CRobT(\TaskName:=cellctlMotionTask \Tool:=cellctlTool \WObj:=cellctlWobj);
            head := "# 0 " + date + " " + time + " " + NumToStr(ClkRead(timer), 2) + " ";
            SocketSend clientSocket \Str:=head;
            SocketSend clientSocket \Str:=NumToStr(pose.trans.x, 4) + " " + NumToStr(pose.trans.y, 4) + " " + NumToStr(pose.trans.z, 4) + " ";
            SocketSend clientSocket \Str:=NumToStr(pose.rot.q1, 6) + " " + NumToStr(pose.rot.q2, 6) + " " + NumToStr(pose.rot.q3, 6) + " " + NumToStr(pose.rot.q4, 6) + NL;
            WaitForStop;

            joints := CJointT(\TaskName:=cellctlMotionTask);
            head := "# 1 " + date + " " + time + " " + NumToStr(ClkRead(timer), 2) + " ";
            SocketSend clientSocket \Str:=head;
            SocketSend clientSocket \Str:=NumToStr(joints.robax.rax_1, 4) + " " + NumToStr(joints.robax.rax_2, 4) + " " + NumToStr(joints.robax.rax_3, 4) + " ";
            SocketSend clientSocket \Str:=NumToStr(joints.robax.rax_4, 4) + " " + NumToStr(joints.robax.rax_5, 4) + " " + NumToStr(joints.robax.rax_6, 4) + NL;
            WaitForStop;
        ENDWHILE
    ERROR
        IF ERRNO = ERR_SOCK_CLOSED THEN
            ! The client left: wait for the next one.
            SocketClose clientSocket;
            SocketAccept serverSocket, clientSocket \Time:=WAIT_MAX;
            RETRY;
        ENDIF
    ENDPROC

    ! Wait one period for a request from the client; "97" asks the motion task to stop.
    PROC WaitForStop()
        VAR string incoming;
        SocketReceive clientSocket \Str:=incoming \Time:=cellctlLogPeriod;
        IF StrMatch(incoming, 1, "97") <= StrLen(incoming) THEN
            cellctlStopRequest := TRUE;
        ENDIF
    ERROR
        IF ERRNO = ERR_SOCK_TIMEOUT THEN
            RETURN;  ! nothing this period
        ENDIF
        RAISE;
    ENDPROC
ENDMODULE
