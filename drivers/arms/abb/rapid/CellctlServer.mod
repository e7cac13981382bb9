MODULE CellctlServer
    !========================================================================
    ! cellctl motion server: the open_abb socket protocol, cellctl dialect.
    ! Runs in the motion task (T_ROB1); CellctlLogger.mod runs beside it in a
    ! background task and shares the PERS data below.
    !
    ! Request  "NN p1 p2 ... #"      (at most 80 characters, one at a time)
    ! Reply    "<code> <ok> [data] #" -- unlike the public SERVER.mod, every
    !          reply ends with "#", so the PC reads up to it (no guessing).
    ! ok: 0 bad message / refused target, 1 done,
    !     2 protective stop (collision detection stopped the move),
    !     3 stopped by a stop request (97 on the logger link).
    ! Units: mm, degrees, quaternions q1..q4 (w first).
    !
    ! Codes: 0 ping; 1 MoveL x y z q1 q2 q3 q4; 2 MoveAbsJ j1..j6;
    !   3 get cartesian -> x y z q1 q2 q3 q4; 4 get joints -> j1..j6;
    !   6 tool, 7 work object (x y z q1 q2 q3 q4);
    !   8 speed (v_tcp v_ori [v_leax v_reax]); 9 zone (fine tcp ori zone_ori);
    !   5 external axes -> eax_a..eax_f (9E9: the robot has no such axis);
    !   30 buffer add (7 values), 31 buffer clear, 32 buffer length -> n,
    !   33 buffer execute (MoveL through the buffer);
    !   34 external axes move (6 values: MoveAbsJ, robot axes where they are;
    !      9E9 for each axis the robot does not have, a value for each it has);
    !   35 circle point (7 values, kept for the next 36; nothing moves);
    !   36 MoveC from here through the circle point to x y z q1 q2 q3 q4
    !      (refused without a 35 since the last 36, or on this connection);
    !   97 stop (acknowledged here only when idle: during a move it must come
    !   over the logger link); 98 info -> serial*SWversion*type;
    !   99 close (reply, then the next client).
    ! These are the codes of the public SERVER.mod; 5, 34, 35 and 36 take the
    ! same requests, and reply in this dialect with the checks above.
    !
    ! Stop: while MoveL runs, this task reads nothing from its socket. The
    ! logger task sets cellctlStopRequest; the IPers interrupt below raises
    ! ERR_CELLCTL_STOP into the move, whose error handler stops the robot,
    ! clears the path and replies ok=3.
    !
    ! Motors off / general or emergency stop halt this program: no reply comes
    ! and the PC's move time-out expires (it then drops the link).
    !========================================================================

    ! Shared with CellctlLogger (same names in both tasks)
    PERS tooldata cellctlTool := [TRUE,[[0,0,0],[1,0,0,0]],[0.001,[0,0,0.001],[1,0,0,0],0,0,0]];
    PERS wobjdata cellctlWobj := [FALSE,TRUE,"",[[0,0,0],[1,0,0,0]],[[0,0,0],[1,0,0,0]]];
    PERS bool cellctlStopRequest := FALSE;
    ! Controller address the server binds: 192.168.125.1 on the service port,
    ! "127.0.0.1" in a RobotStudio virtual controller.
    PERS string cellctlIp := "192.168.125.1";
    PERS num cellctlMotionPort := 5000;
    ! Check reach with CalcJointT before a MoveL (refuse with ok=0 instead of
    ! stopping the program on "position outside reach").
    PERS bool cellctlCheckReach := TRUE;

    CONST num OK_BAD := 0;
    CONST num OK_DONE := 1;
    CONST num OK_PSTOP := 2;
    CONST num OK_STOPPED := 3;
    CONST num MAX_BUFFER := 512;
    CONST num MAX_PARAMS := 10;

    VAR socketdev serverSocket;
    VAR socketdev clientSocket;
    VAR num code;
    VAR num params{MAX_PARAMS};
    VAR num nParams;
    VAR num ok;
    VAR speeddata currentSpeed;
    VAR zonedata currentZone;
    VAR extjoint externalAxis;
    VAR robtarget bufferTargets{MAX_BUFFER};
    VAR speeddata bufferSpeeds{MAX_BUFFER};
    VAR num bufferCount := 0;
    VAR robtarget circPoint;
    VAR bool haveCircPoint := FALSE;
    VAR bool moving := FALSE;
    VAR intnum stopInterrupt;
    VAR errnum ERR_CELLCTL_STOP := -1;

    PROC main()
        VAR string msg;
        VAR string data;
        VAR bool closeAfter;

        ConfL \Off;
        SingArea \Wrist;
        Initialize;
        BookErrNo ERR_CELLCTL_STOP;
        IDelete stopInterrupt;
        CONNECT stopInterrupt WITH StopTrap;
        IPers cellctlStopRequest, stopInterrupt;

        SocketCreate serverSocket;
        SocketBind serverSocket, cellctlIp, cellctlMotionPort;
        SocketListen serverSocket;
        AcceptClient;

        WHILE TRUE DO
            ReceiveMessage msg;
            ParseMessage msg;
            ok := OK_BAD;
            data := "";
            closeAfter := FALSE;
            IF nParams >= 0 THEN
                Execute data, closeAfter;
            ENDIF
            SendReply data;
            IF closeAfter THEN
                SocketClose clientSocket;
                AcceptClient;
            ENDIF
        ENDWHILE
    ERROR
        IF ERRNO = ERR_SOCK_CLOSED OR ERRNO = ERR_SOCK_TIMEOUT THEN
            ! The client vanished: serve the next one.
            SocketClose clientSocket;
            AcceptClient;
            RETRY;
        ENDIF
    ENDPROC

    PROC Initialize()
        VAR jointtarget now;
        cellctlTool := [TRUE,[[0,0,0],[1,0,0,0]],[0.001,[0,0,0.001],[1,0,0,0],0,0,0]];
        cellctlWobj := [FALSE,TRUE,"",[[0,0,0],[1,0,0,0]],[[0,0,0],[1,0,0,0]]];
        cellctlStopRequest := FALSE;
        currentSpeed := [100, 50, 0, 0];
        currentZone := fine;
        bufferCount := 0;
        now := CJointT();
        externalAxis := now.extax;  ! external axes stay where they are
    ENDPROC

    PROC AcceptClient()
        VAR string clientIp;
        haveCircPoint := FALSE;  ! a circle point is never carried over to the next client
        SocketAccept serverSocket, clientSocket \ClientAddress:=clientIp \Time:=WAIT_MAX;
        TPWrite "CELLCTL: client " + clientIp;
    ENDPROC

    ! Read until the "#" that ends a request (TCP may split it).
    PROC ReceiveMessage(INOUT string msg)
        VAR string chunk;
        msg := "";
        WHILE StrMatch(msg, 1, "#") > StrLen(msg) DO
            SocketReceive clientSocket \Str:=chunk \Time:=WAIT_MAX;
            IF StrLen(msg) + StrLen(chunk) > 80 THEN
                msg := "-1 #";  ! too long for a RAPID string: answered as a bad message
                RETURN;
            ENDIF
            msg := msg + chunk;
        ENDWHILE
    ENDPROC

    ! Tokens separated by spaces up to "#": the code, then up to MAX_PARAMS numbers.
    ! nParams = -1 marks a message that cannot be read.
    PROC ParseMessage(string msg)
        VAR num hashPos;
        VAR num pos := 1;
        VAR num tokenEnd;
        VAR string token;
        VAR bool haveCode := FALSE;

        code := -1;
        nParams := 0;
        hashPos := StrMatch(msg, 1, "#");
        WHILE pos < hashPos DO
            IF StrPart(msg, pos, 1) = " " THEN
                pos := pos + 1;
            ELSE
                tokenEnd := StrFind(msg, pos, " #");
                token := StrPart(msg, pos, tokenEnd - pos);
                pos := tokenEnd;
                IF NOT haveCode THEN
                    IF NOT StrToVal(token, code) THEN
                        code := -1;
                        nParams := -1;
                        RETURN;
                    ENDIF
                    haveCode := TRUE;
                ELSEIF nParams >= MAX_PARAMS THEN
                    nParams := -1;
                    RETURN;
                ELSE
                    nParams := nParams + 1;
                    IF NOT StrToVal(token, params{nParams}) THEN
                        nParams := -1;
                        RETURN;
                    ENDIF
                ENDIF
            ENDIF
        ENDWHILE
        IF NOT haveCode THEN
            nParams := -1;
        ENDIF
    ENDPROC

    PROC SendReply(string data)
        VAR string reply;
        reply := NumToStr(code, 0) + " " + NumToStr(ok, 0) + " ";
        IF data <> "" THEN
            reply := reply + data + " ";
        ENDIF
        SocketSend clientSocket \Str:=reply + "#";
    ENDPROC

    FUNC bool UnitQuaternion(num q1, num q2, num q3, num q4)
        RETURN Abs(Sqrt(q1 * q1 + q2 * q2 + q3 * q3 + q4 * q4) - 1) < 0.001;
    ENDFUNC

    FUNC robtarget TargetFromParams()
        VAR robtarget target;
        target := [[params{1}, params{2}, params{3}],
                   [params{4}, params{5}, params{6}, params{7}],
                   [0, 0, 0, 0],
                   externalAxis];
        target.rot := NOrient(target.rot);
        RETURN target;
    ENDFUNC

    FUNC bool FrameParamsOk()
        RETURN nParams = 7 AND UnitQuaternion(params{4}, params{5}, params{6}, params{7});
    ENDFUNC

    ! An external axis value as sent: 9E9 for an axis that is not there; else
    ! at most 10 characters, so that six of them fit a reply of 80.
    FUNC string AxisToStr(num value)
        IF value > 1E9 THEN
            RETURN "9E9";
        ELSEIF Abs(value) < 10000 THEN
            RETURN NumToStr(value, 4);
        ELSEIF Abs(value) < 1000000 THEN
            RETURN NumToStr(value, 2);
        ENDIF
        RETURN NumToStr(value, 0);
    ENDFUNC

    ! Code 34's six values against the axes the robot has: a value for each
    ! axis it has (CJointT reports 9E9 for the others), 9E9 for each it lacks.
    FUNC bool ExtaxParamsOk(extjoint now)
        VAR num current{6};
        current := [now.eax_a, now.eax_b, now.eax_c, now.eax_d, now.eax_e, now.eax_f];
        FOR i FROM 1 TO 6 DO
            IF (current{i} > 1E9) <> (params{i} > 1E9) THEN
                RETURN FALSE;
            ENDIF
        ENDFOR
        RETURN TRUE;
    ENDFUNC

    ! MoveC's limits (RAPID reference): start, circle point and end at least
    ! 0.1 mm apart and, seen from the start, 1..179 degrees between the circle
    ! point and the end (three points on one line make no circle).
    FUNC bool CircleOk(pos start, pos via, pos target)
        VAR num cosAngle;
        IF VectMagn(via - start) < 0.1 OR VectMagn(target - start) < 0.1 OR VectMagn(target - via) < 0.1 THEN
            RETURN FALSE;
        ENDIF
        cosAngle := DotProd(via - start, target - start) / (VectMagn(via - start) * VectMagn(target - start));
        RETURN cosAngle < Cos(1) AND cosAngle > Cos(179);
    ENDFUNC

    PROC Execute(INOUT string data, INOUT bool closeAfter)
        VAR robtarget pose;
        VAR jointtarget joints;

        TEST code
        CASE 0:  ! ping
            IF nParams = 0 ok := OK_DONE;
        CASE 1:  ! MoveL
            IF FrameParamsOk() THEN
                DoMoveL TargetFromParams(), currentSpeed;
            ENDIF
        CASE 2:  ! MoveAbsJ
            IF nParams = 6 THEN
                joints := [[params{1}, params{2}, params{3}, params{4}, params{5}, params{6}], externalAxis];
                DoMoveAbsJ joints;
            ENDIF
        CASE 3:  ! cartesian pose of the current tool in the current work object
            IF nParams = 0 THEN
                pose := CRobT(\Tool:=cellctlTool \WObj:=cellctlWobj);
                data := NumToStr(pose.trans.x, 4) + " " + NumToStr(pose.trans.y, 4) + " " + NumToStr(pose.trans.z, 4) + " ";
                data := data + NumToStr(pose.rot.q1, 6) + " " + NumToStr(pose.rot.q2, 6) + " ";
                data := data + NumToStr(pose.rot.q3, 6) + " " + NumToStr(pose.rot.q4, 6);
                ok := OK_DONE;
            ENDIF
        CASE 4:  ! joints
            IF nParams = 0 THEN
                joints := CJointT();
                data := NumToStr(joints.robax.rax_1, 4) + " " + NumToStr(joints.robax.rax_2, 4) + " ";
                data := data + NumToStr(joints.robax.rax_3, 4) + " " + NumToStr(joints.robax.rax_4, 4) + " ";
                data := data + NumToStr(joints.robax.rax_5, 4) + " " + NumToStr(joints.robax.rax_6, 4);
                ok := OK_DONE;
            ENDIF
        CASE 5:  ! external axes where they are (9E9: no such axis)
            IF nParams = 0 THEN
                joints := CJointT();
                data := AxisToStr(joints.extax.eax_a) + " " + AxisToStr(joints.extax.eax_b) + " ";
                data := data + AxisToStr(joints.extax.eax_c) + " " + AxisToStr(joints.extax.eax_d) + " ";
                data := data + AxisToStr(joints.extax.eax_e) + " " + AxisToStr(joints.extax.eax_f);
                ok := OK_DONE;
            ENDIF
        CASE 6:  ! tool
            IF FrameParamsOk() THEN
                cellctlTool.tframe := [[params{1}, params{2}, params{3}], [params{4}, params{5}, params{6}, params{7}]];
                cellctlTool.tframe.rot := NOrient(cellctlTool.tframe.rot);
                ok := OK_DONE;
            ENDIF
        CASE 7:  ! work object (object frame; the user frame stays identity)
            IF FrameParamsOk() THEN
                cellctlWobj.oframe := [[params{1}, params{2}, params{3}], [params{4}, params{5}, params{6}, params{7}]];
                cellctlWobj.oframe.rot := NOrient(cellctlWobj.oframe.rot);
                ok := OK_DONE;
            ENDIF
        CASE 8:  ! speed
            IF (nParams = 4 OR nParams = 2) AND params{1} > 0 AND params{2} > 0 THEN
                currentSpeed.v_tcp := params{1};
                currentSpeed.v_ori := params{2};
                IF nParams = 4 THEN
                    currentSpeed.v_leax := params{3};
                    currentSpeed.v_reax := params{4};
                ENDIF
                ok := OK_DONE;
            ENDIF
        CASE 9:  ! zone: fine flag, pzone_tcp, pzone_ori, zone_ori
            IF nParams = 4 THEN
                IF params{1} = 1 THEN
                    currentZone := fine;
                ELSE
                    currentZone.finep := FALSE;
                    currentZone.pzone_tcp := params{2};
                    currentZone.pzone_ori := params{3};
                    currentZone.pzone_eax := params{3};
                    currentZone.zone_ori := params{4};
                    currentZone.zone_leax := params{3};
                    currentZone.zone_reax := params{4};
                ENDIF
                ok := OK_DONE;
            ENDIF
        CASE 30:  ! buffer add (refused when full, not silently dropped)
            IF FrameParamsOk() AND bufferCount < MAX_BUFFER THEN
                bufferCount := bufferCount + 1;
                bufferTargets{bufferCount} := TargetFromParams();
                bufferSpeeds{bufferCount} := currentSpeed;
                ok := OK_DONE;
            ENDIF
        CASE 31:  ! buffer clear
            IF nParams = 0 THEN
                bufferCount := 0;
                ok := OK_DONE;
            ENDIF
        CASE 32:  ! buffer length
            IF nParams = 0 THEN
                data := NumToStr(bufferCount, 0);
                ok := OK_DONE;
            ENDIF
        CASE 33:  ! buffer execute; stops at the first target that fails
            IF nParams = 0 THEN
                ok := OK_DONE;
                FOR i FROM 1 TO bufferCount DO
                    IF ok = OK_DONE THEN
                        DoMoveL bufferTargets{i}, bufferSpeeds{i};
                    ENDIF
                ENDFOR
            ENDIF
        CASE 34:  ! external axes move; the robot axes stay where they are
            IF nParams = 6 THEN
                joints := CJointT();
                IF ExtaxParamsOk(joints.extax) THEN
                    joints.extax := [params{1}, params{2}, params{3}, params{4}, params{5}, params{6}];
                    DoMoveAbsJ joints;
                    joints := CJointT();
                    externalAxis := joints.extax;  ! later MoveL targets keep the axes where they now are
                ENDIF
            ENDIF
        CASE 35:  ! circle point of the next MoveC
            IF FrameParamsOk() THEN
                circPoint := TargetFromParams();
                haveCircPoint := TRUE;
                ok := OK_DONE;
            ENDIF
        CASE 36:  ! MoveC through the circle point of the last 35
            IF FrameParamsOk() AND haveCircPoint THEN
                haveCircPoint := FALSE;
                pose := CRobT(\Tool:=cellctlTool \WObj:=cellctlWobj);
                IF CircleOk(pose.trans, circPoint.trans, [params{1}, params{2}, params{3}]) THEN
                    DoMoveC circPoint, TargetFromParams(), currentSpeed;
                ENDIF
            ENDIF
        CASE 97:  ! stop while idle: nothing is moving
            IF nParams = 0 ok := OK_DONE;
        CASE 98:  ! info
            IF nParams = 0 THEN
                data := GetSysInfo(\SerialNo) + "*" + GetSysInfo(\SWVersion) + "*" + GetSysInfo(\RobotType);
                ok := OK_DONE;
            ENDIF
        CASE 99:  ! close: reply, then wait for the next client
            IF nParams = 0 THEN
                ok := OK_DONE;
                closeAfter := TRUE;
            ENDIF
        DEFAULT:
            ok := OK_BAD;
        ENDTEST
    ENDPROC

    ! Sets ok: done, refused (out of reach), protective stop, stopped by request.
    PROC DoMoveL(robtarget target, speeddata speed)
        VAR jointtarget check;
        IF cellctlCheckReach THEN
            check := CalcJointT(target, cellctlTool \WObj:=cellctlWobj);
        ENDIF
        cellctlStopRequest := FALSE;
        moving := TRUE;
        MoveL target, speed, currentZone, cellctlTool \WObj:=cellctlWobj;
        moving := FALSE;
        ok := OK_DONE;
    ERROR
        moving := FALSE;
        TEST ERRNO
        CASE ERR_ROBLIMIT, ERR_OUTSIDE_REACH:
            ok := OK_BAD;
        CASE ERR_CELLCTL_STOP:
            StopMove;
            ClearPath;
            StartMove;
            ok := OK_STOPPED;
        CASE ERR_COLL_STOP:
            StopMove;
            ClearPath;
            StartMove;
            ok := OK_PSTOP;
        DEFAULT:
            RAISE;
        ENDTEST
        RETURN;
    ENDPROC

    ! Like DoMoveL, for MoveC: both points checked for reach first.
    PROC DoMoveC(robtarget via, robtarget target, speeddata speed)
        VAR jointtarget check;
        IF cellctlCheckReach THEN
            check := CalcJointT(via, cellctlTool \WObj:=cellctlWobj);
            check := CalcJointT(target, cellctlTool \WObj:=cellctlWobj);
        ENDIF
        cellctlStopRequest := FALSE;
        moving := TRUE;
        MoveC via, target, speed, currentZone, cellctlTool \WObj:=cellctlWobj;
        moving := FALSE;
        ok := OK_DONE;
    ERROR
        moving := FALSE;
        TEST ERRNO
        CASE ERR_ROBLIMIT, ERR_OUTSIDE_REACH:
            ok := OK_BAD;
        CASE ERR_CELLCTL_STOP:
            StopMove;
            ClearPath;
            StartMove;
            ok := OK_STOPPED;
        CASE ERR_COLL_STOP:
            StopMove;
            ClearPath;
            StartMove;
            ok := OK_PSTOP;
        DEFAULT:
            RAISE;
        ENDTEST
        RETURN;
    ENDPROC

    PROC DoMoveAbsJ(jointtarget target)
        cellctlStopRequest := FALSE;
        moving := TRUE;
        MoveAbsJ target, currentSpeed, currentZone, cellctlTool \WObj:=cellctlWobj;
        moving := FALSE;
        ok := OK_DONE;
    ERROR
        moving := FALSE;
        TEST ERRNO
        CASE ERR_CELLCTL_STOP:
            StopMove;
            ClearPath;
            StartMove;
            ok := OK_STOPPED;
        CASE ERR_COLL_STOP:
            StopMove;
            ClearPath;
            StartMove;
            ok := OK_PSTOP;
        DEFAULT:
            RAISE;
        ENDTEST
        RETURN;
    ENDPROC

    ! A stop request from the logger task: long-jump out of the move in progress.
    ! With no move instruction running, the robot may still be on the corner
    ! path of a fly-by point (a via point: its MoveL returned, and was answered,
    ! before the robot got there): stop it and drop the rest of its path.
    TRAP StopTrap
        IF cellctlStopRequest AND moving THEN
            RAISE ERR_CELLCTL_STOP;
        ELSEIF cellctlStopRequest THEN
            StopMove;
            ClearPath;
            StartMove;
        ENDIF
    ERROR
        RAISE;
    ENDTRAP
ENDMODULE
